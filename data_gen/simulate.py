"""Integrate trajectories of a reference system, in parallel and reproducibly.

Trajectory b draws its initial state from its own generator,
``SeedSequence(seed, spawn_key=(b,))`` (= ``SeedSequence(seed).spawn(B)[b]``), so the
data do not depend on the number of workers, on how trajectories are chunked, or on B
(the first 10 trajectories of a 1000-trajectory file are those of a 10-trajectory file).
A trajectory that fails (solver error, non-finite state, leaving the system's valid
region) is re-drawn from the same generator, at most ``max_tries`` times.

Stiffness switch.  When the scene's integrator is explicit (RK23, RK45, DOP853) each
trajectory is first integrated with it under a budget of ``STIFF_NFEV_PER_STEP`` (200)
right-hand-side evaluations per saved step (counted by wrapping the RHS: DOP853 spends 12
per step, so this is ~16 accepted steps per dt).  The attempt is declared stiff, abandoned
and redone from the SAME initial state with the implicit ``FALLBACK_METHOD`` (Radau, same
rtol/atol) when

* it exceeds that budget (the step size is held down by stability, not accuracy: the
  non-stiff reference systems need 2-30 evaluations per step at rtol = atol = 1e-9), or
* the explicit solver gives up (solve_ivp status -1, e.g. "required step size is less than
  spacing between numbers": step-size collapse).

Leaving the valid region (the pendulum guard) or a non-finite state is not stiffness: the
trajectory is re-drawn as before (after the fallback has failed too, if it was tried).  The
decision depends only on the trajectory's initial state, so it is reproducible like the data.
`generate` records it: attributes ``fallback_integrator`` and ``fallback_used`` (how many
trajectories needed it) and ``aux/integrator_fallback`` [B] (1 where trajectory b was
integrated with the fallback), so every trajectory can be re-integrated with its own method.
Implicit scene integrators (Radau, BDF, LSODA) run as they are, without budget.
"""
import secrets

import numpy as np
from scipy.integrate import solve_ivp

from mpnode.base.errors import NumericalError
from mpnode.data import Trajectories
from mpnode.runs.executors import chunk_ranges, map_chunks, open_executor

from .initial import draw_initial, get_sampler
from .invariants import invariant_name
from .per_trajectory import scene_graphs
from .scenes import check_scene
from .systems import get_system

#: explicit solve_ivp methods, the ones the stiffness switch watches
EXPLICIT_METHODS = ("RK23", "RK45", "DOP853")
#: the implicit method a stiff trajectory is redone with
FALLBACK_METHOD = "Radau"
#: RHS evaluations per saved step an explicit attempt may spend before it is declared stiff
STIFF_NFEV_PER_STEP = 200


class StiffnessDetected(NumericalError):
    """An explicit integration gave up or exceeded its evaluation budget (see the module docstring)."""


def generate(scene, *, workers=2, max_tries=10, progress=None, scheduler=None):
    """The trajectories of ``scene``, with all it takes to re-integrate them (Trajectories).

    scheduler : where the trajectories are integrated (mpnode.runs.executors: None, the local pool of
    ``workers`` processes; "local", an address or a scheduler file: Dask); the data do not depend on it.
    Root attributes: the system's scalar parameters (spec names), state_names, seed, system_seed,
    integrator, rtol, atol, scene, description, initial, redrawn, and what graphs were built;
    `params/`: the drawn arrays (lorenz H, kuramoto omega).  The graph of trajectory b is
    graph b mod G; a system whose nodes and edges differ has one weighted graph per trajectory and
    its node attributes (data_gen.per_trajectory).  Raises InputError for a bad scene,
    NumericalError if trajectories keep failing.
    """
    check_scene(scene, scene.name)
    system = get_system(scene.system)
    made = scene_graphs(scene)
    for g in made.graphs:
        system.check_graph(g, scene.name, "graph")
    if system.generator is not None:  # closed loop (quadrotor_load): its own driver, controls and aux data
        return system.generator(scene, workers=workers, max_tries=max_tries, progress=progress, scheduler=scheduler)
    n_nodes = scene.graph.n_nodes
    scalars = {**system.defaults, **scene.params}
    drawn = system.draw(scalars, n_nodes, np.random.default_rng(scene.system_seed))
    sampler = get_sampler(scene.initial, system, n_nodes, scene.name, "initial")
    x, redraws, fallback = simulate(system.name, {**scalars, **drawn}, made.graphs, made.graph_index, sampler,
                                    scene.horizon, scene.dt, scene.seed, method=scene.integrator, rtol=scene.rtol,
                                    atol=scene.atol, max_tries=max_tries, workers=workers, progress=progress,
                                    return_fallback=True, scheduler=scheduler, node_attrs=made.node_attrs)
    attrs = dict(scalars, seed=scene.seed, system_seed=scene.system_seed, integrator=scene.integrator,
                 rtol=scene.rtol, atol=scene.atol, scene=scene.name, description=scene.description,
                 initial=scene.initial, max_tries=max_tries, redrawn=int(redraws.sum()), **made.attrs)
    aux = dict(made.aux)
    if scene.integrator in EXPLICIT_METHODS:
        attrs.update(fallback_integrator=FALLBACK_METHOD, fallback_used=int(fallback.sum()),
                     stiff_nfev_per_step=STIFF_NFEV_PER_STEP)
        aux["integrator_fallback"] = fallback.astype(np.int8)
    if scene.initial == "uniform":
        attrs.update(initial_low=np.asarray(system.low), initial_high=np.asarray(system.high))
    if system.state_names:
        attrs["state_names"] = list(system.state_names)
    if invariant_name(system.name):
        attrs["invariant"] = invariant_name(system.name)
    graphs, gi = made.graphs, made.graph_index
    return Trajectories(x=x, graphs=graphs, dt=scene.dt, system=system.name,
                        graph_index=gi if len(graphs) > 1 else None, attrs=attrs, params=drawn, aux=aux,
                        **made.trajectory_fields())


def integrate(rhs, x0, n_steps, dt, method="DOP853", rtol=1e-9, atol=1e-9, guard=None, max_nfev=None):
    """One trajectory saved at t = k*dt, k = 0..n_steps.

    rhs : f(t, y) on the flat state, shape (N*dx,);  x0 : shape (N, dx)
    guard : g(t, y) > 0 while the state is valid (stops the solver as a terminal event), or None
    max_nfev : with an explicit method, raise StiffnessDetected once the RHS has been evaluated
        more than this many times or the solver gives up (step-size collapse); None: no budget
    Returns x : shape (n_steps+1, N, dx); raises NumericalError saying why it failed.
    """
    x0 = np.asarray(x0, dtype=np.float64)
    t_eval = np.arange(n_steps + 1) * dt  # k*dt, not accumulated
    events = None
    if guard is not None:
        if guard(0.0, x0.ravel()) <= 0:
            raise NumericalError("initial state is outside the region where the system is defined")
        events = _terminal(guard)
    watch = max_nfev is not None and method in EXPLICIT_METHODS
    if watch:
        rhs = _Budget(rhs, max_nfev)
    try:
        sol = solve_ivp(rhs, (0.0, t_eval[-1]), x0.ravel(), method=method, t_eval=t_eval,
                        rtol=rtol, atol=atol, events=events)
    except _OverBudget:
        raise StiffnessDetected(f"{method} needed more than {max_nfev} right-hand-side evaluations") from None
    except (ValueError, ArithmeticError) as e:  # e.g. Radau's LU of a Jacobian holding inf: the physics blew up
        raise NumericalError(f"{method} failed: {e}") from None
    reached = np.asarray(sol.t)  # a failed solve with t_eval may return an empty list
    reached = float(reached[-1]) if reached.size else 0.0
    if watch and sol.status == -1:
        raise StiffnessDetected(f"{method} gave up before t = {reached:g} (the last saved time): {sol.message}")
    if sol.status != 0:
        why = "left the region where the system is defined" if sol.status == 1 else sol.message
        raise NumericalError(f"solver stopped after t = {reached:g}: {why}")
    if not np.all(np.isfinite(sol.y)):
        raise NumericalError("non-finite state")
    if guard is not None and np.any(guard(None, sol.y) <= 0):
        raise NumericalError("a saved state is outside the region where the system is defined")
    return sol.y.T.reshape(n_steps + 1, *x0.shape)


def integrate_switching(rhs, x0, n_steps, dt, method="DOP853", rtol=1e-9, atol=1e-9, guard=None,
                        fallback=FALLBACK_METHOD, nfev_per_step=STIFF_NFEV_PER_STEP):
    """`integrate` with the stiffness switch of the module docstring.

    Returns (x, used): x shape (n_steps+1, N, dx); used is ``method`` or ``fallback`` (the
    latter when the explicit attempt was declared stiff).  NumericalError if both fail.
    """
    if method not in EXPLICIT_METHODS or fallback is None:
        return integrate(rhs, x0, n_steps, dt, method, rtol, atol, guard), method
    try:
        return integrate(rhs, x0, n_steps, dt, method, rtol, atol, guard,
                         max_nfev=nfev_per_step * max(1, n_steps)), method
    except StiffnessDetected:
        return integrate(rhs, x0, n_steps, dt, fallback, rtol, atol, guard), fallback


class _OverBudget(Exception):
    pass


class _Budget:
    """The RHS, counting its calls and raising _OverBudget past ``limit``."""

    def __init__(self, rhs, limit):
        self.rhs, self.limit, self.nfev = rhs, limit, 0

    def __call__(self, t, y):
        self.nfev += 1
        if self.nfev > self.limit:
            raise _OverBudget
        return self.rhs(t, y)


def _terminal(guard):
    def event(t, y):
        return guard(t, y)

    event.terminal = True
    return event


def simulate(system, params, graphs, graph_index, sampler, n_steps, dt, seed, *,
             method="DOP853", rtol=1e-9, atol=1e-9, max_tries=10, workers=2, progress=None,
             fallback=FALLBACK_METHOD, return_fallback=False, scheduler=None, node_attrs=None):
    """Integrate B = len(graph_index) trajectories of ``system``.

    params : scalar and drawn array parameters (see systems.make_rhs)
    graphs : list of Graph;  graph_index : shape (B,), the graph of each trajectory
    sampler : sampler(rng, system, n_nodes) -> x0 of shape (N, dx), picklable (initial.py)
    progress : called with the number of trajectories just finished, or None
    fallback : the implicit method of the stiffness switch (module docstring), None to switch it off
    workers, scheduler : see mpnode.runs.executors.open_executor (workers=1 without a scheduler: in this process)
    node_attrs : (B, N, dp), each trajectory's node attributes, for a system whose nodes differ; or None
    Returns (x, redraws): x shape (B, n_steps+1, N, dx) float64, redraws shape (B,) int;
    with ``return_fallback`` also used_fallback, shape (B,) bool (True: integrated with ``fallback``).
    Raises NumericalError when a trajectory still fails after ``max_tries`` initial states.
    """
    job = dict(system=system, params=params, graphs=graphs, graph_index=np.asarray(graph_index),
               sampler=sampler, n_steps=n_steps, dt=dt, seed=seed, method=method, rtol=rtol,
               atol=atol, max_tries=max_tries, fallback=fallback, node_attrs=node_attrs, token=secrets.token_hex(8))
    B = len(graph_index)
    x = np.empty((B, n_steps + 1, graphs[0].n_nodes, get_system(system).state_dim))
    redraws = np.zeros(B, dtype=np.int64)
    used_fallback = np.zeros(B, dtype=bool)

    def keep(chunk, result):
        x[chunk.start:chunk.stop], redraws[chunk.start:chunk.stop], used_fallback[chunk.start:chunk.stop] = result
        if progress is not None:
            progress(len(chunk))

    if workers == 1 and scheduler is None:
        try:
            map_chunks(None, _run_job, job, chunk_ranges(B, 1, 25), keep)
        finally:
            _PREPARED.clear()
    else:
        with open_executor(scheduler, workers) as farm:
            map_chunks(farm, _run_job, job, chunk_ranges(B, farm.workers, 25), keep)
    return (x, redraws, used_fallback) if return_fallback else (x, redraws)


# ---- worker side: a process prepares a job once (its right-hand sides), then runs chunks of it ----
_PREPARED = {}


def _run_job(job, chunk):
    """Trajectories ``chunk`` of ``job``, preparing the job in this process the first time."""
    prepared = _PREPARED.get(job["token"])
    if prepared is None:
        system = get_system(job["system"])
        shared = job["node_attrs"] is None  # else each trajectory's rhs is made when it runs (_rhs_of)
        prepared = dict(job, sys=system, rhs=[system.rhs(job["params"], g) for g in job["graphs"]] if shared else None)
        _PREPARED.clear()  # one job at a time per process: the last one's RHS are dropped
        _PREPARED[job["token"]] = prepared
    return _run(prepared, chunk)


def _run(j, chunk):
    """Trajectories ``chunk`` (a range of b) of the prepared job ``j``:
    x (len, T+1, N, dx), redraws (len,), used_fallback (len,)."""
    xs, rs, fs = [], [], []
    for b in chunk:
        rng = np.random.default_rng(np.random.SeedSequence(j["seed"], spawn_key=(b,)))
        g = int(j["graph_index"][b])
        graph, rhs = j["graphs"][g], _rhs_of(j, b, g)
        attrs = None if j["node_attrs"] is None else j["node_attrs"][b]
        for tries in range(j["max_tries"]):
            x0 = draw_initial(j["sampler"], rng, j["sys"], graph, attrs, j["params"])
            try:
                x, used = integrate_switching(rhs, x0, j["n_steps"], j["dt"], j["method"], j["rtol"], j["atol"],
                                              j["sys"].guard, fallback=j["fallback"])
                xs.append(x)
                fs.append(used != j["method"])
                break
            except NumericalError as e:
                problem = e
        else:
            raise NumericalError(f"{j['system']}: trajectory {b} failed for {j['max_tries']} initial "
                                 f"states in a row (last: {problem}); check the parameters and dt")
        rs.append(tries)
    return np.stack(xs), np.asarray(rs, dtype=np.int64), np.asarray(fs, dtype=bool)


def _rhs_of(j, b, g):
    """The right-hand side of trajectory b (on graph g) of the prepared job ``j``."""
    if j["rhs"] is not None:
        return j["rhs"][g]
    return j["sys"].rhs(j["params"], j["graphs"][g], j["node_attrs"][b])
