"""Quantities the true dynamics of a system conserve, so that `mpnode eval` can show how far a
learned rollout drifts from them (the physics stays here; mpnode.evaluation takes a callable).

A generated file names its system's invariant in the attribute ``invariant``; `invariant_of`
turns a file into the function x (B, T+1, N, dx) -> (B, T+1) that computes it.
"""
from functools import partial
from inspect import signature

import numpy as np


def pendulum_energy(x, graph, m, l, k, g):
    """The coupled pendulums' conserved energy.  Their equation (data_gen.systems.pendulum_rhs) is,
    in s = sin(theta), m l s'' = -m g s - k l (s_i - s_j): harmonic oscillators coupled by springs,
    whose energy sum_i (m l^2 s_i'^2 + m g l s_i^2) / 2 + sum_edges k l^2 (s_i - s_j)^2 / 2 stays
    constant (s' = omega cos(theta)).  x (B, T+1, N, 2) = [theta, omega] per node."""
    theta, omega = x[..., 0], x[..., 1]
    s, ds = np.sin(theta), omega * np.cos(theta)
    nodes = 0.5 * (m * l**2 * ds**2 + m * g * l * s**2)
    pairs = graph.edges()
    pairs = pairs[pairs[:, 0] < pairs[:, 1]]  # each undirected edge once
    springs = 0.5 * k * l**2 * (s[..., pairs[:, 0]] - s[..., pairs[:, 1]]) ** 2
    return nodes.sum(axis=-1) + springs.sum(axis=-1)


#: the invariant of each system that has one: (name, function of x, the graph and the file's parameters)
INVARIANTS = {"coupled_pendulum": ("energy", pendulum_energy)}


def invariant_name(system):
    """The name of ``system``'s invariant, or None (recorded in generated files as ``invariant``)."""
    return INVARIANTS[system][0] if system in INVARIANTS else None


def invariant_of(traj):
    """(name, x -> (B, T+1)) of ``traj``'s invariant (the one its file names, by default its
    system's), with the file's parameters and its graph; None when there is none, or the file
    lacks a parameter or has several graphs."""
    known = INVARIANTS.get(traj.system)
    if known is None or traj.attrs.get("invariant", known[0]) != known[0] or len(traj.graphs) != 1:
        return None
    names = [p for p in signature(known[1]).parameters if p not in ("x", "graph")]
    if not all(p in traj.attrs for p in names):
        return None
    return known[0], partial(known[1], graph=traj.graphs[0], **{p: float(traj.attrs[p]) for p in names})
