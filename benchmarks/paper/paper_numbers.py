"""The MP-NODE paper's published numbers that the suite sets beside its own, in one place so
that every experiment quotes the same value."""

#: Table 1 (gene16): validation on the training graphs ("seen": MP-NODE and L2S), test on unseen
#: BA, ER and WS graphs (MP-NODE only)
TABLE1 = {"mpnode": {"seen": 0.0051, "ba": 0.0045, "er": 0.0026, "ws": 0.0023}, "l2s": {"seen": 0.0106}}

#: Table 2 (min test error x epochs), MP-NODE (fine-tuned, from scratch) by column (system, training
#: trajectories); gene: 4x4 -> 8x8
TABLE2 = {("lorenz", 50): (632.70, 12800), ("lorenz", 100): (833.91, 10454), ("lorenz", 500): (477.75, 5656),
          ("kuramoto", 50): (1358.50, 5008), ("kuramoto", 100): (1264.83, 5268), ("kuramoto", 500): (874.80, 3974),
          ("gene", 100): (12.53, 28.0)}

#: Table 2's gene column with its L2S cell, by the suite's run that sets each beside it
TABLE2_GENE = {"gene64_ft_default": TABLE2["gene", 100][0], "gene64_scratch_default": TABLE2["gene", 100][1],
               "gene64_ft_l2s": 46.64}

#: Table 2's quadrotor column (3 -> 6 quadrotors): MP-NODE fine-tuned and L2S fine-tuned (from scratch: N/A)
TABLE2_QUAD = {"q6_ft_m20": 236.0, "q6_ft_l2s": 476.0}
