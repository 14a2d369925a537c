"""What a model file says about where it came from, set against the data it meets.

A model records the system of its training data (``attrs["system"]``).  Meeting data of
another system with the same sizes is allowed -- a user may transfer a model on purpose --
but never silently: `system_mismatch` words the warning that `mpnode eval`, `simulate`
and `finetune` print.
"""


def system_mismatch(model, system, source):
    """A warning (one sentence) when ``model`` was trained on another system than ``system``
    (the data's, named by ``source``); None when they agree or the model does not say."""
    trained = model.attrs.get("system")
    if not isinstance(trained, str) or not trained or trained == system:
        return None
    return (f"the model was trained on {trained} data, but {source} holds {system}: the systems differ, so expect "
            f"large errors unless this transfer is meant (train or fine-tune on {system} data otherwise)")
