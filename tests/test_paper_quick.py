"""The paper suite's --quick mode end to end (benchmarks/paper): every experiment trains,
analyses and reports, and the speed-against-error numbers behave as numerics say they must.
The run takes minutes: its tests are in the slow tier (`pytest -m slow`)."""
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")

SUITE = Path(__file__).resolve().parents[1] / "benchmarks" / "paper" / "run_all.py"


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper")
    proc = subprocess.run([sys.executable, str(SUITE), "--quick", "--out", str(out)], cwd=out,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out


@pytest.mark.slow
def test_results_has_every_section_and_figure(quick_run):
    text = (quick_run / "RESULTS.md").read_text()
    for title in ("1. Messages matter", "2. Zero-shot to unseen topologies", "3. Zero-shot to more nodes",
                  "4. Fine-tuning", "5. Message size", "6. Speed against error", "7. Aggregation",
                  "8. Learning-rate schedule", "9. Quadrotor swarm",
                  "10. Messages against a monolithic neural ODE", "11. The paper's integrator",
                  "12. The paper's Tables 1 and 2", "13. Batch size at equal wall time"):
        assert f"## {title}" in text
    for fig in ("messages_loss", "fig2_pendulum", "fig3b_no_messages", "kuramoto_trajectories", "finetune_curves",
                "fig6_gene_grid_8x8", "fig6_gene_grid_4x4_er", "message_size", "speed_vs_error", "schedule_val_loss",
                "quadrotor_message_size", "fig9_quadrotor_finetune", "batch_val_loss"):
        png = quick_run / "figures" / f"{fig}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"figures/{fig}.png" in text
    assert text.count("Paper's caption") >= 7  # Fig. 2, 3a, 3b, 4, 6a, 6b, 9 quote the paper beside ours


@pytest.mark.slow
def test_tables_set_every_column_beside_the_paper(quick_run):
    tables = (quick_run / "sections" / "exp_tables.md").read_text()
    for cell in ("validation, BA (training graphs)", "test, WS (unseen)", "Lorenz10 ds=50", "Kuramoto ds=50",
                 "Gene, paper's settings", "Gene, defaults + L2S", "Quadrotors 3 -> 6", "(632.7)", "(1358.5)"):
        assert cell in tables, cell


@pytest.mark.slow
def test_every_run_completed(quick_run):
    for path in (quick_run / "work" / "runs").glob("*/result.json"):
        res = json.loads(path.read_text())
        assert res["status"] == "completed", (path, res["message"])
        assert res["epochs"] == res["options"]["epochs"]


@pytest.mark.slow
def test_aggregation_runs_use_the_recipes_aggregations(quick_run):
    numbers = json.loads((quick_run / "results" / "aggregation.json").read_text())
    assert {name: (numbers[name]["aggregation"], numbers[name]["linear_aggregation"]) for name in
            ("gene16_paper_mean", "gene16_scaled", "gene16_scaled_heldout", "gene16_default", "gene16_l2s",
             "gene16_paper_mean_hot")} == {
        "gene16_paper_mean": ("mean", None), "gene16_scaled": ("scaled", None),
        "gene16_scaled_heldout": ("scaled", None), "gene16_default": ("mean", "scaled"), "gene16_l2s": ("sum", None),
        "gene16_paper_mean_hot": ("mean", None)}
    assert all(v["nmse"] > 0 for case in ("gene16_default", "gene16_l2s") for k, v in numbers[case].items()
               if isinstance(v, dict))


@pytest.mark.slow
def test_a_plain_node_refuses_a_graph_of_another_size(quick_run):
    numbers = json.loads((quick_run / "results" / "node.json").read_text())
    assert "13" in numbers["refusal"] and "10" in numbers["refusal"]  # kuramoto10's NODE asked for 13 nodes


@pytest.mark.slow
def test_finetune_curves_and_determinism(quick_run):
    numbers = json.loads((quick_run / "results" / "finetune.json").read_text())
    assert set(numbers) == {"lorenz10_50", "lorenz10_100", "lorenz10_500", "gene64", "kuramoto_er_50"}
    for case in numbers.values():
        ft, sc = case["finetune"], case["scratch"]
        assert ft["nmse"]["curve"][0] == [0, ft["zero_shot_nmse"]]  # fine-tuning's epoch 0: the source model
        assert len(sc["nmse"]["curve"]) == 2  # scratch's epoch-0 point is not a model fit starts from
        for run in (ft, sc):
            assert run["status"] == "completed"
            assert len(run["paper_units"]["curve"]) == len(run["nmse"]["curve"])
            assert run["paper_units"]["product"] > 0 and run["nmse"]["product"] > 0
    # in quick mode the three Lorenz10 sizes are the same 6 trajectories: separately trained (maybe in
    # different processes), the runs must agree exactly -- training is deterministic given its seed
    curves = [[numbers[f"lorenz10_{n}"][who]["paper_units"]["curve"] for who in ("finetune", "scratch")]
              for n in (50, 100, 500)]
    assert curves[0] == curves[1] == curves[2]


@pytest.mark.slow
def test_speed_against_error_obeys_the_numerics(quick_run):
    numbers = json.loads((quick_run / "results" / "speed.json").read_text())
    assert len(numbers) == 4
    for system, rows in numbers.items():
        def errors(family, dtype="float64"):
            return [r["nmse"] for r in rows if r["family"] == family and r["dtype"] == dtype]

        # tighter tolerances and more RK4 substeps converge to the truth (down to round-off)
        for fam in ("scipy DOP853", "scipy RK45", "RK4, true field"):
            e = errors(fam)
            assert e[-1] < 1e-10, (system, fam, e)
            assert all(b <= a * 1.5 or b < 1e-16 for a, b in zip(e, e[1:])), (system, fam, e)
        # the batched true-field RK4 is the same arithmetic as the one-at-a-time loop
        batch = errors("RK4, true field, batch")
        if system != "kuramoto10 (BA)":  # its right-hand side does not broadcast over trajectories
            assert len(batch) == 4
        assert all(math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-20) for a, b in zip(batch, errors("RK4, true field")))
        # the learned model: the same weights in float32 and float64 predict the same
        e32, e64 = errors("MP-NODE, batch", "float32"), errors("MP-NODE, batch", "float64")
        assert all(math.isclose(a, b, rel_tol=1e-2) for a, b in zip(e32, e64)), (system, e32, e64)
        assert all(r["seconds_per_trajectory"] > 0 for r in rows)


def test_short_run_trains_a_share_of_every_full_run_on_the_same_data():
    """--short is the full run scaled down: the same runs, data and settings, SHARE of each epoch
    count and wall-time budget, so that its tables compare with RESULTS.md's."""
    import importlib

    sys.path.insert(0, str(SUITE.parent))
    try:
        common = importlib.import_module("common")
        def specs(mode):
            return {s.name: s for name in common.EXPERIMENTS for s in importlib.import_module(name).runs(mode)}
        full, short = specs(common.Mode("full")), specs(common.Mode("short"))
    finally:
        sys.path.remove(str(SUITE.parent))
    share = common.SHORT_SHARE
    assert set(full) == set(short)
    for name, f in full.items():
        s = short[name]
        limit = dict(f.extra).get("time_limit")
        assert (s.train, s.test, s.init_from, s.test_points) == (f.train, f.test, f.init_from, f.test_points), name
        if limit is None:
            assert s.epochs == round(f.epochs * share), name
        else:
            assert dict(s.extra)["time_limit"] == pytest.approx(limit * share) and s.epochs == f.epochs, name
