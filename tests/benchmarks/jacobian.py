"""The refinement's Jacobian two ways, both integrated with `hamid.refine.dop853`: forward
differences (hamid's way) against the variational equations (issue 22).

    python tests/benchmarks/jacobian.py [--repeats 7] [--segments 64 256]

For a batch of segments (4 dominant periods each, as the refinement cuts conftest's
records: 20.96 s of peng-quadratic, 22.69 s of Duffing; 0.05 s sampling), cut from
noise-free `hamid.simulate` trajectories at the true parameters, the derivatives of the
states at every sample by each segment's initial state (2N) and the parameters (p) are
computed

- (a) by forward differences: 1 + 2N + p copies of each segment's state, the initial
  states perturbed by `trajectory.STEP` times each variable's scale and the parameters by
  `STEP * max(|theta|, 1e-3 max |theta|)`, as `hamid.refine.trajectory` does, with its atol
  (1e-2 rtol times each variable's scale, the same for every copy); `a diff` with the
  hand-written right-hand side, and `a hamid` with hamid's own (`Dynamics.at`, as the
  refinement integrates: the same values, a check that `a diff` is hamid's way, and
  hamid's cost per call; not part of the comparison);
- (b) by the variational equations: the state and its sensitivity matrix S (2N x (2N + p)),
  dS/dt = J_x S + [0 | df/dtheta], with the analytic derivatives; the atol of S[s, c] is
  the state's atol divided by the scale of variable c (S times that scale is the change
  of x_s by a relative change of c, held to x_s's atol), `b all`; or the error control on
  the state only, `b state`: S's atol infinite, and the state's rtol and atol times
  sqrt(2N / values), since DOP853's error norm is a root mean square over all values
  (without it the state's tolerance would loosen by sqrt(1 + 2N + p)).

Both integrate the same number of values, 2N (1 + 2N + p) per segment, as one system, the
right-hand sides written by hand here in vectorised numpy (neither uses hamid's
`Dynamics`), from the same table of q's monomials, filled in place: (a) with each copy's
coefficients folded once per integration (as hamid folds its polynomial coefficients) and
summed by one einsum, (b) as one product of a matrix (a, da/dq, da/dtheta by the
monomials) with the table, and da/dq S by one einsum. Printed per case: the median wall
time of `--repeats` integrations (alternated, after one of each to warm up), its ratio to
(a)'s and that of the shortest times and of the median CPU times (the surer ones when
other work shares the cores); the steps taken (rejected included) and the median share of
the time spent in the right-hand side (each call timed) and its cost per call (`rhs µs`,
the best of 500 calls); and the accuracy against a reference, the variational equations at
rtol 1e-12 with `scipy.integrate.solve_ivp` (itself checked against central differences of
`solve_ivp` at rtol 1e-12 on two segments, and the hand-written equations against
`hamid.simulate`): the largest error of a Jacobian column relative to that column's
largest value (`x0 col`, `theta col`), the largest relative error of J'J's diagonal (`JJ
diag`), and the error of the parameters' Gauss-Newton step from a residual of pure noise,
in the reference's standard errors (`GN step`; the bundle adjustment of
`trajectory._Normal.step`): about how far the Jacobian's error moves the estimates.

numpy's BLAS runs on one thread (`OPENBLAS_NUM_THREADS=1` unless set): the stepper's
products of an 11,000-value system on the threaded BLAS of 2 shared cores took 1-20x
longer, at random, for either method.
"""

# ruff: noqa: E402  (the thread limits must be set before numpy is imported)
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import dataclasses
import sys
import time
import timeit
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
RTOLS = (1e-8, 1e-11)   # hamid's loose and strict tolerances


@dataclass(frozen=True)
class Equations:
    """Hand-written equations of a conservative system q'' = a(q, theta), polynomial in q
    and affine in theta: a and its derivatives are the product `terms(theta) @ M`, rows a
    (N), da/dq (N x N, row by row), da/dtheta (N x p, row by row), where
    `monomials(q, M)` writes q's monomials into M but for its first row, ones.
    `accel(q, theta)` (N, ...) is a, written out again, independently, to check them."""

    accel: Callable
    monomials: Callable
    terms: Callable


def _peng(q, th):
    (u1, u2), (w1, w2, a1, a2, a3, a6) = q, th
    return np.array([-w1 * u1 + a1 * u1**2 + a2 * u1 * u2 + a3 * u2**2,
                     -w2 * u2 + a2 * u1**2 / 2 + 2 * a3 * u1 * u2 + a6 * u2**2])


def _peng_monomials(q, out):
    u1, u2 = q
    out[1:3] = q
    np.multiply(u1, u1, out=out[3])
    np.multiply(u1, u2, out=out[4])
    np.multiply(u2, u2, out=out[5])


def _peng_terms(th):
    w1, w2, a1, a2, a3, a6 = th
    # columns: 1, u1, u2, u1^2, u1 u2, u2^2
    return np.array([[0, -w1, 0, a1, a2, a3],                  # a1
                     [0, 0, -w2, a2 / 2, 2 * a3, a6],          # a2
                     [-w1, 2 * a1, a2, 0, 0, 0],               # da1/du1
                     [0, a2, 2 * a3, 0, 0, 0],                 # da1/du2
                     [0, a2, 2 * a3, 0, 0, 0],                 # da2/du1
                     [-w2, 2 * a3, 2 * a6, 0, 0, 0],           # da2/du2
                     [0, -1, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0],  # da1/dtheta
                     [0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 0],
                     [0, 0, 0, 0, 0, 1], [0, 0, 0, 0, 0, 0],
                     [0, 0, 0, 0, 0, 0], [0, 0, -1, 0, 0, 0],  # da2/dtheta
                     [0, 0, 0, 0, 0, 0], [0, 0, 0, 0.5, 0, 0],
                     [0, 0, 0, 0, 2, 0], [0, 0, 0, 0, 0, 1]], dtype=float)


def _duffing(q, th):
    (x,), (k, k3) = q, th
    return np.array([-k * x - k3 * x * x * x])


def _duffing_monomials(q, out):
    (x,) = q
    out[1] = x
    np.multiply(x, x, out=out[2])
    np.multiply(out[2], x, out=out[3])


def _duffing_terms(th):
    k, k3 = th
    return np.array([[0, -k, 0, -k3],            # a
                     [-k, 0, -3 * k3, 0],        # da/dx
                     [0, -1, 0, 0], [0, 0, 0, -1]], dtype=float)   # da/dk, da/dk3


PENG_EQUATIONS = Equations(_peng, _peng_monomials, _peng_terms)
DUFFING_EQUATIONS = Equations(_duffing, _duffing_monomials, _duffing_terms)


@dataclass(frozen=True)
class Batch:
    """Segments of a built-in model to differentiate: start states (B, 2N), sample
    times, true theta (p,), each variable's scale (2N,) and weight (2N,)."""

    model: str
    equations: Equations
    x0: np.ndarray
    times: np.ndarray
    theta: np.ndarray
    scale: np.ndarray
    weight: np.ndarray

    @property
    def theta_scale(self) -> np.ndarray:
        return np.maximum(np.abs(self.theta), 1e-3 * np.abs(self.theta).max())

    @property
    def columns_scale(self) -> np.ndarray:
        """The scale of each variable differentiated by: the states', then theta's."""
        return np.concatenate([self.scale, self.theta_scale])


@dataclass(frozen=True)
class System:
    """What `dop853.integrate` is given, and the Jacobian (B, m, 2N, c) from its values."""

    fun: Callable
    y0: np.ndarray
    rtol: float
    atol: np.ndarray
    jacobian: Callable


def forward_differences(batch: Batch, rtol: float, hamid_rhs: bool = False) -> System:
    """(a): 1 + 2N + p copies of each segment, hamid's steps and atol; with `hamid_rhs`,
    hamid's own right-hand side (`Dynamics.at`) in place of the hand-written one."""
    from hamid.refine import trajectory

    x0, theta = batch.x0, batch.theta
    B, n2 = x0.shape
    n, p = n2 // 2, len(theta)
    c = n2 + p
    steps = trajectory.STEP * batch.columns_scale
    starts = np.repeat(x0[:, :, None], 1 + c, axis=2)              # (B, 2N, copies)
    starts[:, np.arange(n2), 1 + np.arange(n2)] += steps[:n2]
    W = np.repeat(theta[:, None, None], B, axis=1).repeat(1 + c, axis=2)   # (p, B, copies)
    W[np.arange(p), :, 1 + n2 + np.arange(p)] += steps[n2:, None]
    # the columns segment by segment, each segment's copies together (as hamid's)
    y0 = starts.transpose(1, 0, 2).reshape(n2, -1)
    # a's coefficients of the monomials, each copy its own (affine in theta), folded
    # once per integration as hamid folds its polynomial coefficients
    eq = batch.equations
    G0 = eq.terms(np.zeros(p))[:n]
    by_theta = np.array([eq.terms(e)[:n] - G0 for e in np.eye(p)])       # (p, N, monomials)
    C = G0[..., None] + np.einsum("kim,kc->imc", by_theta, W.reshape(p, -1))
    M = np.ones((C.shape[1], y0.shape[1]))

    def fun(_t, y):
        Y = y.reshape(n2, -1)
        out = np.empty_like(Y)
        out[:n] = Y[n:]
        eq.monomials(Y[:n], M)
        np.einsum("imc,mc->ic", C, M, out=out[n:])
        return out.ravel()

    if hamid_rhs:
        from hamid.model.dissipation import Dissipation
        from hamid.model.dynamics import Dynamics
        from hamid.model.models import builtin_model

        model = builtin_model(batch.model)
        fun = Dynamics(model, Dissipation(model.coordinates, model.velocities)).at(
            np.concatenate([np.ones((1, y0.shape[1])), W.reshape(p, -1)]))
    atol = np.repeat(1e-2 * rtol * batch.scale, y0.shape[1])

    def jacobian(values):
        V = values.reshape(len(values), n2, B, 1 + c)
        return ((V[..., 1:] - V[..., :1]) / steps).transpose(2, 0, 1, 3)
    return System(fun, y0.ravel(), rtol, atol, jacobian)


def variational(batch: Batch, rtol: float, state_only: bool = False) -> System:
    """(b): each segment's state and sensitivities S (2N, 2N + p); the error control on
    all values, or `state_only`."""
    x0, theta = batch.x0, batch.theta
    B, n2 = x0.shape
    n, p = n2 // 2, len(theta)
    c = n2 + p
    Y0 = np.zeros((n2, 1 + c, B))
    Y0[:, 0] = x0.T
    Y0[np.arange(n2), 1 + np.arange(n2)] = 1.0
    G = batch.equations.terms(theta)
    monomials = batch.equations.monomials
    M = np.ones((G.shape[1], B))

    def fun(_t, y):
        Y = y.reshape(n2, 1 + c, B)
        out = np.empty_like(Y)
        out[:n] = Y[n:]                                  # x' = v and S_q' = S_v
        monomials(Y[:n, 0], M)
        R = G @ M
        out[n:, 0] = R[:n]
        H = R[n:n + n * n].reshape(n, n, B)              # da/dq
        np.einsum("ijb,jcb->icb", H, Y[:n, 1:], out=out[n:, 1:])   # da/dq S_q
        out[n:, 1 + n2:] += R[n + n * n:].reshape(n, p, B)
        return out.ravel()

    atol = np.empty((n2, 1 + c, B))
    atol[:, 0] = 1e-2 * rtol * batch.scale[:, None]
    atol[:, 1:] = (np.inf if state_only
                   else atol[:, :1] / batch.columns_scale[None, :, None])
    shrink = (1 / (1 + c)) ** 0.5 if state_only else 1.0   # the state's share of the RMS
    atol[:, 0] *= shrink

    def jacobian(values):
        return values.reshape(len(values), n2, 1 + c, B)[:, :, 1:].transpose(3, 0, 1, 2)
    return System(fun, Y0.ravel(), rtol * shrink, atol.ravel(), jacobian)


METHODS = {"a diff": forward_differences,
           "a hamid": lambda batch, rtol: forward_differences(batch, rtol, hamid_rhs=True),
           "b all": variational,
           "b state": lambda batch, rtol: variational(batch, rtol, state_only=True)}


@dataclass(frozen=True)
class Run:
    """One integration: the Jacobian (B, m, 2N, c), its wall and CPU seconds, the steps
    (taken and rejected) and the seconds in the right-hand side (each call timed: 0.2 µs
    of 20-50)."""

    jacobian: np.ndarray | None
    seconds: float
    cpu: float
    steps: int
    rhs: float


def run(label: str, batch: Batch, rtol: float) -> Run:
    from hamid.refine import dop853

    system = METHODS[label](batch, rtol)
    fun, step = system.fun, dop853._step
    steps, rhs = [0], [0.0]

    def call(t, y):
        begin = time.perf_counter()
        out = fun(t, y)
        rhs[0] += time.perf_counter() - begin
        return out

    def counting(*a):
        steps[0] += 1
        return step(*a)
    dop853._step = counting
    try:
        begin, cpu = time.perf_counter(), time.process_time()
        values = dop853.integrate(call, system.y0, batch.times, system.rtol, system.atol,
                                  10**6)
        seconds, cpu = time.perf_counter() - begin, time.process_time() - cpu
    finally:
        dop853._step = step
    return Run(system.jacobian(values), seconds, cpu, steps[0], rhs[0])


def call_cost(label: str, batch: Batch) -> float:
    """Seconds per call of the right-hand side at the start, the best of 5 x 100 calls
    (little moved by other work on the cores)."""
    system = METHODS[label](batch, 1e-8)
    return min(timeit.repeat(lambda: system.fun(0.0, system.y0), number=100, repeat=5)) / 100


def reference(batch: Batch) -> np.ndarray:
    """The variational equations at rtol 1e-12 with scipy's DOP853 (B, m, 2N, c)."""
    from scipy.integrate import solve_ivp

    system = variational(batch, 1e-12)
    solution = solve_ivp(system.fun, (0.0, batch.times[-1]), system.y0, method="DOP853",
                         t_eval=batch.times, rtol=system.rtol, atol=system.atol)
    return system.jacobian(solution.y.T)


def motion(batch: Batch, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """One segment's states from x under theta by `accel`, solve_ivp at rtol 1e-12."""
    from scipy.integrate import solve_ivp

    n, accel = len(x) // 2, batch.equations.accel

    def fun(_t, y):
        return np.concatenate([y[n:], accel(y[:n], theta)])
    return solve_ivp(fun, (0.0, batch.times[-1]), x, method="DOP853", t_eval=batch.times,
                     rtol=1e-12, atol=1e-14 * batch.scale).y.T


def simulation_error(batch: Batch, first: np.ndarray) -> float:
    """The hand-written equations against hamid's simulation: the largest difference over
    the first segment's samples, relative to the scales."""
    return float(np.max(np.abs(motion(batch, first[0], batch.theta) - first) / batch.scale))


def reference_error(batch: Batch, ref: np.ndarray) -> float:
    """The reference's largest column error against central differences of `motion`
    (steps of 1e-4 of the scales) on two segments."""
    x0, theta = batch.x0, batch.theta
    n2 = x0.shape[1]
    h = 1e-4 * batch.columns_scale
    worst = 0.0
    for b in range(2):
        columns = []
        for k in range(len(h)):
            shift = np.zeros(len(h))
            shift[k] = h[k]
            up = motion(batch, x0[b] + shift[:n2], theta + shift[n2:])
            down = motion(batch, x0[b] - shift[:n2], theta - shift[n2:])
            columns.append((up - down) / (2 * h[k]))
        worst = max(worst, column_error(np.stack(columns, axis=-1)[None], ref[b:b + 1],
                                        batch.weight))
    return worst


def column_error(J: np.ndarray, ref: np.ndarray, weight: np.ndarray) -> float:
    """The largest error of a column (one segment's derivatives by one variable, every
    sample and state weighted) relative to that column's largest value."""
    w = weight[None, None, :, None]
    error = np.abs((J - ref) * w).max(axis=(1, 2))
    return float(np.max(error / np.abs(ref * w).max(axis=(1, 2))))


def accuracy(J: np.ndarray, ref: np.ndarray, batch: Batch, noise: np.ndarray
             ) -> dict[str, float]:
    """The Jacobian's errors against the reference: columns, J'J's diagonal, the
    Gauss-Newton step of the parameters from a residual of pure noise (standard errors)."""
    n2, w = batch.x0.shape[1], batch.weight
    out = {"x0 col": column_error(J[..., :n2], ref[..., :n2], w),
           "theta col": column_error(J[..., n2:], ref[..., n2:], w)}

    def normal(J):
        Jw = J * w[None, None, :, None]
        H = np.einsum("bmsc,bmsd->bcd", Jw, Jw)
        g = np.einsum("bmsc,bms->bc", Jw, noise)
        return H, g
    H, g = normal(J)
    H_ref, g_ref = normal(ref)
    diag, diag_ref = np.einsum("bcc->bc", H), np.einsum("bcc->bc", H_ref)
    out["JJ diag"] = float(np.max(np.abs(diag - diag_ref) / diag_ref))

    def step(H, g):
        inverse = np.linalg.inv(H[:, :n2, :n2])
        H_xt = H[:, :n2, n2:]
        schur = (H[:, n2:, n2:].sum(axis=0)
                 - np.einsum("sak,sab,sbl->kl", H_xt, inverse, H_xt))
        rhs = g[:, n2:].sum(axis=0) - np.einsum("sak,sab,sb->k", H_xt, inverse, g[:, :n2])
        return np.linalg.solve(schur, rhs), schur
    d, _ = step(H, g)
    d_ref, schur = step(H_ref, g_ref)
    out["GN step"] = float(np.max(np.abs(d - d_ref) / np.sqrt(np.diag(np.linalg.inv(schur)))))
    return out


def cut(system: dict, equations: Equations, length: float, segments: int
        ) -> tuple[Batch, np.ndarray]:
    """`segments` segments of `length` seconds from the system's trajectories, simulated
    long enough, noise-free; weights of 1% noise."""
    import hamid

    dt = system["simulate"]["dt"]
    samples = int(round(length / dt)) + 1
    per_trajectory = -(-segments // len(system["initial"]))
    t_end = per_trajectory * (samples - 1) * dt + dt
    frame = hamid.simulate({**system, "simulate": {**system["simulate"], "t_end": t_end}})
    X = frame.iloc[:, 2:].to_numpy()
    starts = []
    for _, rows in frame.groupby("trajectory").indices.items():
        starts.extend(X[rows[0] + k * (samples - 1)] for k in range(per_trajectory))
    scale = np.maximum(np.abs(X).max(axis=0), X.std(axis=0))   # as trajectory's x_step / STEP
    # the first segment's samples, to check the hand-written equations against
    first = X[:samples]
    batch = Batch(system["model"]["builtin"], equations, np.array(starts[:segments]),
                  np.arange(samples) * dt, np.array(list(system["parameters"].values()), float),
                  scale, 1 / (0.01 * X.std(axis=0)))
    return batch, first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--segments", type=int, nargs="+", default=[64, 256])
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import DUFFING, PENG

    cases = {"peng-quadratic (2 DOF)": (PENG, PENG_EQUATIONS, 20.96),
             "duffing (1 DOF)": (DUFFING, DUFFING_EQUATIONS, 22.69)}
    rng = np.random.default_rng(0)
    print(f"{'case':34} {'method':8} {'rtol':>6} {'ms':>8} {'/ a':>6} {'min/a':>6} "
          f"{'cpu/a':>6} {'steps':>6} {'rhs %':>6} {'rhs µs':>7} {'x0 col':>8} "
          f"{'theta col':>9} {'JJ diag':>8} {'GN step':>8}")
    for name, (system, equations, length) in cases.items():
        for segments in args.segments:
            batch, first = cut(system, equations, length, segments)
            ref = reference(batch)
            simulated = simulation_error(batch, first)
            ref_error = reference_error(batch, ref)
            print(f"{name}, {segments} segments of {len(batch.times)} samples: equations vs "
                  f"hamid.simulate {simulated:.1e}, reference vs central differences "
                  f"{ref_error:.1e}")
            noise = rng.standard_normal(ref.shape[:3])
            for rtol in RTOLS:
                warm = {label: run(label, batch, rtol) for label in METHODS}
                runs = {label: [] for label in METHODS}
                for _ in range(args.repeats):
                    for label in METHODS:
                        # without its Jacobian: 38 MB for 256 segments of peng-quadratic
                        runs[label].append(dataclasses.replace(run(label, batch, rtol),
                                                               jacobian=None))
                seconds = {label: [r.seconds for r in runs[label]] for label in METHODS}
                cpu = {label: np.median([r.cpu for r in runs[label]]) for label in METHODS}
                base, fastest = np.median(seconds["a diff"]), min(seconds["a diff"])
                for label, warm_run in warm.items():
                    errors = accuracy(warm_run.jacobian, ref, batch, noise)
                    median = np.median(seconds[label])
                    share = np.median([r.rhs / r.seconds for r in runs[label]])
                    print(f"{'':34} {label:8} {rtol:6.0e} {1e3 * median:8.1f} "
                          f"{median / base:6.2f} {min(seconds[label]) / fastest:6.2f} "
                          f"{cpu[label] / cpu['a diff']:6.2f} "
                          f"{warm_run.steps:6d} {100 * share:6.0f} "
                          f"{1e6 * call_cost(label, batch):7.1f} "
                          f"{errors['x0 col']:8.1e} {errors['theta col']:9.1e} "
                          f"{errors['JJ diag']:8.1e} {errors['GN step']:8.1e}", flush=True)


if __name__ == "__main__":
    main()
