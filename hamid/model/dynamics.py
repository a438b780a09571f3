"""Lagrange's equations of a model, for the simulator and the trajectory refinement.

A natural energy E = T + V (T quadratic in the velocities) gives L = T - V, split like the
energy into L = L0 + sum_k theta_k L_k (`Model.lagrangian`). With the dissipative forces
F_i = -sum_k c_k dR_k/dv_i of a Rayleigh dissipation function (`hamid.model.dissipation`), the
motion follows

    M(q) a = dL/dq - (d/dq dL/dv) v + F,      M = d2L/dv2

(docs/method.md, "The trajectory refinement" and "Damping: the energy balance"), derived
here from the energy and never written per model. Because T is quadratic in v, M depends
on q only, and (d/dq dL/dv) v = ((dM/dq) v) v vanishes when M is constant.

`Dynamics` holds a model and its dissipation; `Dynamics.at` fixes the weights
w = (1, theta, dissipation coefficients) and returns a `Motion`: the accelerations of many
states at once, and solve_ivp's right-hand side. The weights are either

- one vector shared by every state (the simulator): the parts are combined into one
  Lagrangian before deriving, so every call evaluates only that one; or
- one column per state (the refinement, whose copies of a segment each carry perturbed
  parameters for a finite-difference Jacobian): the parts are derived once per model and
  their values weighed state by state.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from hamid.model.dissipation import Dissipation
from hamid.model.expressions import Func, Stack
from hamid.model.models import Model

__all__ = ["Dynamics", "Inputs", "Motion"]

Array = npt.NDArray[np.float64]
# A driven model's inputs at time t, written into the second argument: u(t) of every
# state, (m, n_states), C-contiguous (written, not returned: a driven integrator stage
# then makes no array for them)
Inputs = Callable[[float, Array], None]


@dataclass(frozen=True, eq=False)
class _Stacks:
    """Functions of the same variables, maybe of different kinds (polynomials, compiled
    expressions), each kind compiled into one stack (`Func.stack`)."""

    funcs: tuple[Func, ...]

    @cached_property
    def _kinds(self) -> tuple[tuple[npt.NDArray[np.intp], tuple[Func, ...], Stack], ...]:
        """Per kind: the functions' positions, the functions and their stack."""
        positions: dict[type, list[int]] = {}
        for i, f in enumerate(self.funcs):
            positions.setdefault(type(f), []).append(i)
        kinds = []
        for at in positions.values():
            funcs = tuple(self.funcs[i] for i in at)
            kinds.append((np.array(at, dtype=np.intp), funcs, Func.stack(funcs)))
        return tuple(kinds)

    def combined(self, K: Array) -> Callable[[Array], Array]:
        """sum_k K[g, k, j] f_k(X[:, j]) at states X (variables, n), shape (G, n): K is
        (G, len(funcs), n), one column per state, or (G, len(funcs)), shared by every
        state (then combined into G functions once)."""
        if K.ndim == 3:
            sums = [stack.combined(K[:, at]) for at, _, stack in self._kinds]
        else:
            sums = [Func.stack([Func.combine(funcs, [float(x) for x in row]) for row in K[:, at]])
                    for at, funcs, _ in self._kinds]
        if len(sums) == 1:
            return sums[0]
        return lambda X: sum(values(X) for values in sums)


@dataclass(frozen=True, eq=False)
class _Terms:
    """The pieces of Lagrange's equations for each part L_p of L = sum_p w_p L_p, and the
    applied forces (dissipative and input) beside them.

    Per part: the forces dL_p/dq_i, then the entries (i, k) of d(dL_p/dv_i)/dq_k in
    `mixed` (those not zero in every part), and the upper triangle of the mass matrix
    d2L_p/dv2 in `upper` order. `applied` holds the applied forces' parts, the N
    generalized forces of each over `variables` (q, v, then the inputs u).
    """

    n: int
    mixed: tuple[tuple[int, int], ...]
    upper: tuple[tuple[int, int], ...]
    forces: tuple[tuple[Func, ...], ...]
    mass: tuple[tuple[Func, ...], ...]
    constant_mass: bool
    applied: tuple[tuple[Func, ...], ...]
    variables: tuple[str, ...]

    @classmethod
    def derive(cls, parts: Sequence[Func], coordinates: Sequence[str],
               velocities: Sequence[str], applied: tuple[tuple[Func, ...], ...],
               variables: tuple[str, ...]) -> _Terms:
        N = len(coordinates)
        dv = [[part.diff(v) for v in velocities] for part in parts]
        mixed = tuple((i, k) for i in range(N) for k in range(N)
                      if not all(d[i].diff(coordinates[k]).is_zero() for d in dv))
        # the mass matrix is symmetric: its upper triangle, row by row
        upper = tuple((i, j) for i in range(N) for j in range(i, N))
        mass = tuple(tuple(d[i].diff(velocities[j]) for i, j in upper) for d in dv)
        forces = tuple(tuple([part.diff(q) for q in coordinates]
                             + [d[i].diff(coordinates[k]) for i, k in mixed])
                       for part, d in zip(parts, dv, strict=True))
        constant = all(f.is_constant_in(coordinates) for row in mass for f in row)
        return cls(N, mixed, upper, forces, mass, constant, applied=applied,
                   variables=variables)

    @cached_property
    def force_stack(self) -> _Stacks:
        """The parts' forces and mixed entries, then the applied forces, over `variables`."""
        return self._with_applied([f for row in self.forces for f in row])

    @cached_property
    def mass_stack(self) -> Stack:
        return Func.stack([f for row in self.mass for f in row])

    @cached_property
    def full_stack(self) -> _Stacks:
        """Forces, mixed and mass entries, then the applied forces, in one call, for a mass
        that changes with q."""
        return self._with_applied([f for forces, mass in zip(self.forces, self.mass,
                                                              strict=True)
                                   for f in (*forces, *mass)])

    @cached_property
    def applied_stack(self) -> _Stacks:
        return _Stacks(tuple(f for part in self.applied for f in part))

    def _with_applied(self, funcs: Sequence[Func]) -> _Stacks:
        return _Stacks(tuple(f.over(self.variables) for f in funcs)
                       + self.applied_stack.funcs)


class Dynamics:
    """The equations of motion of a model with a dissipation function.

    Parameters
    ----------
    model : Model
        A model with a natural energy (`Model.lagrangian`).
    dissipation : Dissipation, optional
        Rayleigh's R over the model's state; its coefficients follow theta in the weights,
        in the order of `Dissipation.names`. None: a conservative system.
    """

    def __init__(self, model: Model, dissipation: Dissipation | None = None):
        lagrangian = model.lagrangian
        self.coordinates, self.velocities = lagrangian.coordinates, lagrangian.velocities
        self.n = len(self.coordinates)
        self._parts = (lagrangian.L0, *lagrangian.L)
        self.dissipation = dissipation if dissipation else None
        self.forcing = model.forcing

    @property
    def n_weights(self) -> int:
        """Length of a weight vector: 1, the parameters, the dissipation coefficients."""
        return len(self._parts) + (len(self.dissipation) if self.dissipation else 0)

    @cached_property
    def _applied(self) -> tuple[tuple[tuple[Func, ...], ...], tuple[tuple[int | None, float],
                                                                    ...], tuple[str, ...]]:
        """The applied forces' parts (N functions of (q, v, u) each), each part's weight
        (index into the weights, None for 1, and its sign) and the variables (q, v, u):
        each dissipative term's dR_k/dv (weighed by -c_k), the inputs' Q0 and each Q_k
        (by theta_k)."""
        variables = (*self.coordinates, *self.velocities,
                     *(self.forcing.inputs if self.forcing else ()))
        parts: list[tuple[Func, ...]] = []
        weights: list[tuple[int | None, float]] = []
        if self.dissipation is not None:
            P = len(self._parts)
            for k, part in enumerate(self.dissipation.parts):
                parts.append(tuple(part.diff(v).over(variables) for v in self.velocities))
                weights.append((P + k, -1.0))
        if self.forcing is not None:
            forcing = self.forcing
            for k, row in [(None, forcing.Q0),
                           *((k, tuple(Q[k] for Q in forcing.Q))
                             for k in range(len(forcing.parameters)))]:
                if not all(f.is_zero() for f in row):
                    parts.append(row)
                    weights.append((None if k is None else 1 + k, 1.0))
        return tuple(parts), tuple(weights), variables

    @cached_property
    def _per_part(self) -> _Terms:
        parts, _, variables = self._applied
        return _Terms.derive(self._parts, self.coordinates, self.velocities, parts, variables)

    def at(self, weights: npt.ArrayLike, *, drained: bool = False,
           inputs: Inputs | None = None) -> Motion:
        """The equations at weights (1, theta, dissipation coefficients).

        `weights` has shape (n_weights,), shared by every state, or (n_weights, n_states),
        one column per state (the states passed to the `Motion` must then number n_states).
        With `drained`, the states carry one more row: the energy the damping has drained
        (less the work the inputs supplied) since the start, whose rate is the power -F.v
        (F the dissipative and input forces). A driven model (`Model.forcing`)
        needs its `inputs`: `Inputs`, which write u(t) of every state; their generalized
        force joins the dissipative forces.
        """
        w = np.asarray(weights, dtype=np.float64)
        P = len(self._parts)
        if w.ndim not in (1, 2) or len(w) != self.n_weights:
            raise ValueError(f"weights of shape {w.shape}: expected ({self.n_weights},) or "
                             f"({self.n_weights}, n_states)")
        if (self.forcing is None) != (inputs is None):
            raise ValueError("a driven model's equations need its inputs, a free one's none")
        parts, rows, variables = self._applied
        ones = np.ones(w.shape[1:])
        applied = np.array([ones if k is None else sign * w[k] for k, sign in rows]
                           ).reshape(len(rows), *w.shape[1:])
        if w.ndim == 1:
            lagrangian = Func.combine(self._parts, [float(x) for x in w[:P]])
            terms = _Terms.derive([lagrangian], self.coordinates, self.velocities, parts,
                                  variables)
            return Motion(terms, np.ones(1), applied, drained, inputs)
        return Motion(self._per_part, w[:P], applied, drained, inputs)


class Motion:
    """Lagrange's equations at fixed weights, for many states at once.

    A state array Y holds the variables on its first axis: rows q_1..q_N, v_1..v_N (and,
    with `drained`, the energy drained by the damping); its columns are the states
    (trajectories, or copies of segments). Made by `Dynamics.at`.

    What keeps the calls cheap (each runs once per integrator stage):
    - everything the equations need comes from one compiled call per kind of function
      (`Func.stack`; one in all when the energy, dissipation and work are polynomials):
      the conservative, dissipative and input forces together, over the state and the
      inputs; the parts are weighed state by state inside it when the weights are per
      state (`Stack.combined`: a polynomial's coefficients are weighed once, not its
      values at every call), or combined into one function per output once when shared;
    - a constant mass matrix is inverted once and folded into those weights, so that the
      call returns the accelerations themselves;
    - a changing mass matrix is solved by division (N = 1), Cramer's rule (N = 2, where a
      batched LU costs far more) or LU;
    - a driven model's arguments (q, v, u) are one buffer kept between calls, into which
      the states are copied and the inputs write themselves (`Inputs`).
    """

    def __init__(self, terms: _Terms, weights: Array, applied: Array, drained: bool,
                 inputs: Inputs | None = None):
        self.n = terms.n
        self.rows = 2 * terms.n + bool(drained)
        self.drained = drained
        self.constant_mass = terms.constant_mass
        # the parts' weights (parts,) shared or (parts, n) per state, and the applied
        # forces' (applied parts,) or (applied parts, n)
        self._terms, self._weights, self._applied = terms, weights, applied
        self._shared = weights.ndim == 1
        self._inputs = inputs
        # (q, v, u) of the last call's number of states, reused, and its rows u
        self._arguments = self._input_rows = np.empty((0, 0))
        self._folded = False
        self._inverse: Array | None = None   # (N, N) shared, or (N, N, n) per state
        stack = self._invert_constant_mass() if terms.constant_mass else None
        if stack is None:
            entries = self.n + len(terms.mixed) + len(terms.upper)
            stack = self._weighted(terms.full_stack, self._eye(entries))
        self._values = stack
        self._power = (self._weighted(terms.applied_stack, self._eye(self.n), parts=False)
                       if drained and len(applied) else None)

    def _eye(self, entries: int) -> Array:
        """The identity mixing of `_weighted` (`entries` per part)."""
        return np.eye(entries) if self._shared else np.eye(entries)[..., None]

    def _invert_constant_mass(self) -> Callable[[Array], Array] | None:
        """Invert a constant mass matrix once; the stack that goes with the inverse."""
        N, terms = self.n, self._terms
        M = self.mass_matrix(np.zeros((2 * N, 1 if self._shared else self._weights.shape[1])))
        try:
            inverse = np.linalg.inv(M)
        except np.linalg.LinAlgError:
            # a singular one is no kinetic energy: left to the general path, where the
            # simulator's check names it before any step and the refinement's solve fails
            return None
        self._inverse = inverse[0] if self._shared else inverse.transpose(1, 2, 0).copy()
        if terms.mixed:   # added to the forces before the inverse applies
            return self._weighted(terms.force_stack, self._eye(N + len(terms.mixed)))
        # (dM/dq) v vanishes, and M^-1 (dL/dq + F) are the accelerations
        self._folded = True
        return self._weighted(terms.force_stack, self._inverse)

    def _weighted(self, stacks: _Stacks, mix: Array, *, parts: bool = True
                  ) -> Callable[[Array], Array]:
        """The stack's values summed with the weights, then mixed by `mix` (G, E[, n]): the
        E entries of each part (with `parts`), part after part, then the applied forces
        on the first N entries. A callable of the arguments (q, v[, u]) returning (G, n)."""
        blocks = [(self._weights, mix.shape[1])] if parts else []
        blocks.append((self._applied, self.n))
        K = [mix[:, None, :entries] * weights[None, :, None] for weights, entries in blocks]
        tail = np.broadcast_shapes(*(k.shape[3:] for k in K))
        return stacks.combined(np.concatenate(
            [np.broadcast_to(k, (*k.shape[:3], *tail)).reshape(len(mix), -1, *tail)
             for k in K], axis=1))

    def _apply_inverse(self, x: Array) -> Array:
        """The constant mass matrix's inverse times x (N, n)."""
        assert self._inverse is not None
        if self._inverse.ndim == 2:
            return self._inverse @ x
        return (self._inverse * x).sum(axis=1)

    def mass_matrix(self, Y: Array) -> Array:
        """M at states Y, shape (2N, ...) -> (..., N, N)."""
        stack = self._terms.mass_stack
        if self._shared:
            values = stack(Y)
        else:
            W = self._weights
            K = np.eye(stack.n_funcs // len(W))[:, None, :, None] * W[None, :, None]
            values = stack.combined(K.reshape(len(K), -1, W.shape[1]))(Y)
        return _assemble(values, self._terms.upper, self.n)

    def _arguments_at(self, t: float, Y: Array) -> Array:
        """The stacks' arguments at time t and states Y (2N, n): Y, with the inputs u(t)
        below for a driven model, written into one buffer kept between calls (a new
        array per stage cost a fifth of a driven stage; nothing holds the arguments past
        the call that made them)."""
        if self._inputs is None:
            return Y
        X = self._arguments
        if X.shape[1] != Y.shape[1]:
            X = self._arguments = np.empty((len(self._terms.variables), Y.shape[1]))
            self._input_rows = X[len(Y):]
        X[:len(Y)] = Y
        self._inputs(t, self._input_rows)
        return X

    def accelerations(self, Y: Array, t: float = 0.0) -> Array:
        """a (N, n) at states Y (2N, n) (and time t, for a driven model's inputs)."""
        out = np.empty((self.n, Y.shape[1]))
        self._accelerations(self._arguments_at(t, Y[:2 * self.n]), out)
        return out

    def _accelerations(self, X: Array, out: Array) -> None:
        """The accelerations at the arguments X (q, v[, u]) into `out` (N, n)."""
        values = self._values(X)
        if self._folded:
            out[:] = values
            return
        N, mixed = self.n, self._terms.mixed
        rhs = values[:N]
        V = X[N:2 * N]
        for m, (i, k) in enumerate(mixed):
            rhs[i] -= values[N + m] * V[k]
        if self._inverse is not None:
            out[:] = self._apply_inverse(rhs)
            return
        upper = values[N + len(mixed):]
        if N == 1:
            out[0] = rhs[0] / upper[0]
        elif N == 2:  # Cramer's rule: a batched LU costs far more at this size
            a, b, d = upper
            det = a * d - b * b
            out[0] = (d * rhs[0] - b * rhs[1]) / det
            out[1] = (a * rhs[1] - b * rhs[0]) / det
        else:
            out[:] = np.linalg.solve(_assemble(upper, self._terms.upper, N),
                                     rhs.T[..., None])[..., 0].T

    def __call__(self, t: float, y: Array) -> Array:
        """solve_ivp's right-hand side (q, v[, drained])' = (v, a[, -F.v]), y flattened
        from an array of `rows` rows, one column per state."""
        N = self.n
        Y = y.reshape(self.rows, -1)
        X = self._arguments_at(t, Y[:2 * N])
        out = np.empty_like(Y)
        out[:N] = Y[N:2 * N]
        self._accelerations(X, out[N:2 * N])
        if self.drained:   # the energy's balance: drained by damping, supplied by inputs
            out[2 * N] = (0.0 if self._power is None
                          else -np.einsum("ij,ij->j", self._power(X), Y[N:2 * N]))
        return out.ravel()


def _assemble(upper: Array, order: Sequence[tuple[int, int]], N: int) -> Array:
    """Symmetric matrices (..., N, N) from their upper-triangle entries (len(order), ...)."""
    M = np.empty((*upper.shape[1:], N, N))
    for (i, j), entry in zip(order, upper, strict=True):
        M[..., i, j] = M[..., j, i] = entry
    return M
