"""Integrate trajectories of a reference system, in parallel and reproducibly.

Trajectory b draws its initial state from its own generator,
``SeedSequence(seed, spawn_key=(b,))`` (= ``SeedSequence(seed).spawn(B)[b]``), so the
data do not depend on the number of workers, on how trajectories are chunked, or on B
(the first 10 trajectories of a 1000-trajectory file are those of a 10-trajectory file).
A trajectory that fails (solver error, non-finite state, leaving the system's valid
region) is re-drawn from the same generator, at most ``max_tries`` times.
"""
import math
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np
from scipy.integrate import solve_ivp

from mpnode.data import Trajectories
from mpnode.errors import NumericalError

from .initial import get_sampler
from .scenes import check_scene
from .systems import get_system


def generate(scene, *, workers=2, max_tries=10, progress=None):
    """The trajectories of ``scene``, with all it takes to re-integrate them (Trajectories).

    Root attributes: the system's scalar parameters (spec names), seed, system_seed,
    integrator, rtol, atol, scene, description, initial, redrawn, and what graphs were built;
    `params/`: the drawn arrays (lorenz H, kuramoto omega).  The graph of trajectory b is
    graph b mod G.  Raises InputError for a bad scene, NumericalError if trajectories keep failing.
    """
    check_scene(scene, scene.name)
    system = get_system(scene.system)
    graphs = scene.graph.build()
    for g in graphs:
        system.check_graph(g, scene.name, "graph")
    if system.generator is not None:  # closed loop (quadrotor_load): its own driver, controls and aux data
        return system.generator(scene, workers=workers, max_tries=max_tries, progress=progress)
    n_nodes, B = scene.graph.n_nodes, scene.trajectories
    scalars = {**system.defaults, **scene.params}
    drawn = system.draw(scalars, n_nodes, np.random.default_rng(scene.system_seed))
    sampler = get_sampler(scene.initial, system, n_nodes, scene.name, "initial")
    graph_index = np.arange(B) % len(graphs)
    x, redraws = simulate(system.name, {**scalars, **drawn}, graphs, graph_index, sampler, scene.horizon,
                          scene.dt, scene.seed, method=scene.integrator, rtol=scene.rtol, atol=scene.atol,
                          max_tries=max_tries, workers=workers, progress=progress)
    attrs = dict(scalars, seed=scene.seed, system_seed=scene.system_seed, integrator=scene.integrator,
                 rtol=scene.rtol, atol=scene.atol, scene=scene.name, description=scene.description,
                 initial=scene.initial, max_tries=max_tries, redrawn=int(redraws.sum()),
                 **scene.graph.describe())
    if scene.initial == "uniform":
        attrs.update(initial_low=np.asarray(system.low), initial_high=np.asarray(system.high))
    return Trajectories(x=x, graphs=graphs, dt=scene.dt, system=system.name,
                        graph_index=graph_index if len(graphs) > 1 else None, attrs=attrs, params=drawn)


def integrate(rhs, x0, n_steps, dt, method="DOP853", rtol=1e-9, atol=1e-9, guard=None):
    """One trajectory saved at t = k*dt, k = 0..n_steps.

    rhs : f(t, y) on the flat state, shape (N*dx,);  x0 : shape (N, dx)
    guard : g(t, y) > 0 while the state is valid (stops the solver as a terminal event), or None
    Returns x : shape (n_steps+1, N, dx); raises NumericalError saying why it failed.
    """
    x0 = np.asarray(x0, dtype=np.float64)
    t_eval = np.arange(n_steps + 1) * dt  # k*dt, not accumulated
    events = None
    if guard is not None:
        if guard(0.0, x0.ravel()) <= 0:
            raise NumericalError("initial state is outside the region where the system is defined")
        events = _terminal(guard)
    sol = solve_ivp(rhs, (0.0, t_eval[-1]), x0.ravel(), method=method, t_eval=t_eval,
                    rtol=rtol, atol=atol, events=events)
    if sol.status != 0:
        why = "left the region where the system is defined" if sol.status == 1 else sol.message
        raise NumericalError(f"solver stopped at t = {sol.t[-1] if sol.t.size else 0.0:g}: {why}")
    if not np.all(np.isfinite(sol.y)):
        raise NumericalError("non-finite state")
    if guard is not None and np.any(guard(None, sol.y) <= 0):
        raise NumericalError("a saved state is outside the region where the system is defined")
    return sol.y.T.reshape(n_steps + 1, *x0.shape)


def _terminal(guard):
    def event(t, y):
        return guard(t, y)

    event.terminal = True
    return event


def simulate(system, params, graphs, graph_index, sampler, n_steps, dt, seed, *,
             method="DOP853", rtol=1e-9, atol=1e-9, max_tries=10, workers=2, progress=None):
    """Integrate B = len(graph_index) trajectories of ``system``.

    params : scalar and drawn array parameters (see systems.make_rhs)
    graphs : list of Graph;  graph_index : shape (B,), the graph of each trajectory
    sampler : sampler(rng, system, n_nodes) -> x0 of shape (N, dx), picklable (initial.py)
    progress : called with the number of trajectories just finished, or None
    Returns (x, redraws): x shape (B, n_steps+1, N, dx) float64, redraws shape (B,) int.
    Raises NumericalError when a trajectory still fails after ``max_tries`` initial states.
    """
    job = dict(system=system, params=params, graphs=graphs, graph_index=np.asarray(graph_index),
               sampler=sampler, n_steps=n_steps, dt=dt, seed=seed, method=method, rtol=rtol,
               atol=atol, max_tries=max_tries)
    B = len(graph_index)
    size = max(1, min(25, math.ceil(B / (4 * workers))))
    chunks = [range(i, min(i + size, B)) for i in range(0, B, size)]
    x = np.empty((B, n_steps + 1, graphs[0].n_nodes, get_system(system).state_dim))
    redraws = np.zeros(B, dtype=np.int64)

    def keep(chunk, xs, rs):
        x[chunk.start:chunk.stop], redraws[chunk.start:chunk.stop] = xs, rs
        if progress is not None:
            progress(len(chunk))

    if workers == 1:
        _init(job)
        try:
            for chunk in chunks:
                keep(chunk, *_run(chunk))
        finally:
            _JOB.clear()
    else:
        with ProcessPoolExecutor(workers, initializer=_init, initargs=(job,)) as pool:
            futures = {pool.submit(_run, c): c for c in chunks}
            try:
                for fut in as_completed(futures):
                    keep(futures[fut], *fut.result())
            except BaseException:
                pool.shutdown(cancel_futures=True)
                raise
    return x, redraws


# ---- worker side: the job is set up once per process, then chunks of indices run ----
_JOB = {}


def _init(job):
    system = get_system(job["system"])
    _JOB.clear()
    _JOB.update(job, sys=system, rhs=[system.rhs(job["params"], g) for g in job["graphs"]])


def _run(chunk):
    """Trajectories ``chunk`` (a range of b): x shape (len, T+1, N, dx), redraws shape (len,)."""
    j = _JOB
    xs, rs = [], []
    for b in chunk:
        rng = np.random.default_rng(np.random.SeedSequence(j["seed"], spawn_key=(b,)))
        g = int(j["graph_index"][b])
        n_nodes = j["graphs"][g].n_nodes
        for tries in range(j["max_tries"]):
            x0 = j["sampler"](rng, j["sys"], n_nodes)
            try:
                xs.append(integrate(j["rhs"][g], x0, j["n_steps"], j["dt"], j["method"],
                                    j["rtol"], j["atol"], j["sys"].guard))
                break
            except NumericalError as e:
                problem = e
        else:
            raise NumericalError(f"{j['system']}: trajectory {b} failed for {j['max_tries']} initial "
                                 f"states in a row (last: {problem}); check the parameters and dt")
        rs.append(tries)
    return np.stack(xs), np.asarray(rs, dtype=np.int64)
