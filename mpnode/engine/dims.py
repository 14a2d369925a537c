"""The layout of ``dims``, the tuple of integers that tells the compiled kernels what a model is.

`FieldSpec.dims` builds it and the kernels read it by these names.  Plain integers, no numba:
the kernels' cache is keyed by this file as well as by their own sources, since a kernel
compiled against one layout must not be loaded against another.
"""
#: slots of the tuple
KIND, DX, DU, DM, HIDDEN, SELF_MSG, ZERO_MSG, LINEAR, KINEMATICS = range(9)
N_SLOTS = 9

#: values of dims[KIND]: the field the kernels evaluate (a plain NODE runs as an MP-NODE field
#: without messages on one "node" per system)
MPNODE, L2S = 0, 1

#: bits of dims[LINEAR], the linear aggregate path of an MP-NODE field (mpnode_field)
LINEAR_ON = 1  # the path is there, reading the MLP's aggregate m'
LINEAR_OWN = 2  # it reads its own aggregate s_i m'_i instead (s_i: weight[M + i], see Plan.weight)
LINEAR_STATE = 4  # it adds to dx/dt alone (W_agg has dx columns), not to the messages' dm/dt

#: dims[KINEMATICS]: how many floats of kinematics constants follow the parameters (0: none).
#: Their layout (mpnode.engine.kinematics): a header of HEADER (the pair terms' count, the
#: quaternion terms'), then PAIR_WIDTH floats per pair term and QUATERNION_WIDTH per quaternion
HEADER, PAIR_WIDTH, QUATERNION_WIDTH = 2, 4, 16
