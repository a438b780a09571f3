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

__all__ = ["Dynamics", "Motion"]

Array = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class _Terms:
    """The pieces of Lagrange's equations for each part L_p of L = sum_p w_p L_p.

    Per part: the forces dL_p/dq_i, then the entries (i, k) of d(dL_p/dv_i)/dq_k in
    `mixed` (those not zero in every part), and the upper triangle of the mass matrix
    d2L_p/dv2 in `upper` order.
    """

    n: int
    mixed: tuple[tuple[int, int], ...]
    upper: tuple[tuple[int, int], ...]
    forces: tuple[tuple[Func, ...], ...]
    mass: tuple[tuple[Func, ...], ...]
    constant_mass: bool

    @classmethod
    def derive(cls, parts: Sequence[Func], coordinates: Sequence[str],
               velocities: Sequence[str]) -> _Terms:
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
        return cls(N, mixed, upper, forces, mass, constant)

    @cached_property
    def force_stack(self) -> Stack:
        return Func.stack([f for row in self.forces for f in row])

    @cached_property
    def mass_stack(self) -> Stack:
        return Func.stack([f for row in self.mass for f in row])

    @cached_property
    def full_stack(self) -> Stack:
        """Forces, mixed and mass entries in one call, for a mass that changes with q."""
        return Func.stack([f for forces, mass in zip(self.forces, self.mass, strict=True)
                           for f in (*forces, *mass)])


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
    def _input_parts(self) -> tuple[Stack, npt.NDArray[np.intp], tuple[int | None, ...], int]:
        """The nonzero parts of the inputs' generalized force (Q0 and each Q_k), compiled
        once: their stack over (q, v, u), the coordinate of each, and its parameter (None
        for Q0's parts)."""
        forcing = self.forcing
        assert forcing is not None
        parts = [(i, None, f) for i, f in enumerate(forcing.Q0) if not f.is_zero()]
        parts += [(i, k, g) for i, row in enumerate(forcing.Q) for k, g in enumerate(row)
                  if not g.is_zero()]
        return (Func.stack([f for _, _, f in parts]),
                np.array([i for i, _, _ in parts], dtype=np.intp),
                tuple(k for _, k, _ in parts), self.n)

    @cached_property
    def _per_part(self) -> _Terms:
        return _Terms.derive(self._parts, self.coordinates, self.velocities)

    def at(self, weights: npt.ArrayLike, *, drained: bool = False,
           inputs: Callable[[float], Array] | None = None) -> Motion:
        """The equations at weights (1, theta, dissipation coefficients).

        `weights` has shape (n_weights,), shared by every state, or (n_weights, n_states),
        one column per state (the states passed to the `Motion` must then number n_states).
        With `drained`, the states carry one more row: the energy the damping has drained
        (less the work the inputs supplied) since the start, whose rate is the power -F.v
        (F the dissipative and input forces). A driven model (`Model.forcing`)
        needs its `inputs` as a function of time, u(t) of shape (m,) or (m, n_states);
        their generalized force joins the dissipative forces.
        """
        w = np.asarray(weights, dtype=np.float64)
        P = len(self._parts)
        if w.ndim not in (1, 2) or len(w) != self.n_weights:
            raise ValueError(f"weights of shape {w.shape}: expected ({self.n_weights},) or "
                             f"({self.n_weights}, n_states)")
        if (self.forcing is None) != (inputs is None):
            raise ValueError("a driven model's equations need its inputs, a free one's none")
        forces = None if self.dissipation is None else _Forces(self.dissipation, w[P:])
        driven = None if inputs is None else _InputForces(*self._input_parts, w[1:P], inputs)
        if w.ndim == 1:
            lagrangian = Func.combine(self._parts, [float(x) for x in w[:P]])
            terms = _Terms.derive([lagrangian], self.coordinates, self.velocities)
            return Motion(terms, None, forces, drained, driven)
        return Motion(self._per_part, w[:P], forces, drained, driven)


@dataclass(frozen=True)
class _Forces:
    """The dissipative forces at fixed coefficients (one vector, or a column per state)."""

    dissipation: Dissipation
    coefficients: Array

    def __call__(self, Y: Array) -> Array:
        """F (N, n) at the states Y (2N, n)."""
        return self.dissipation.forces_at(Y, self.coefficients)


class _InputForces:
    """The generalized force of the recorded inputs, Q0 + sum_k theta_k Q_k, at the
    parameters theta (one vector, or a column per state) and the inputs u(t)."""

    def __init__(self, stack: Stack, coordinate: npt.NDArray[np.intp],
                 parameter: tuple[int | None, ...], n: int, theta: Array,
                 inputs: Callable[[float], Array]):
        self.stack, self.inputs = stack, inputs
        ones = np.ones(theta.shape[1:])
        weight = np.array([ones if k is None else theta[k] for k in parameter])
        weight = weight.reshape(len(weight), -1)   # (parts, 1 or n_states)
        # each part into its coordinate's row: with weights shared by every state, folded in
        scatter = (np.arange(n)[:, None] == coordinate[None]).astype(np.float64)
        self.shared = weight.shape[1] == 1
        self.scatter = scatter * weight[:, 0] if self.shared else scatter
        self.weight = weight
        self._arguments: Array | None = None   # (q, v, u) of the last call's shape, reused

    def __call__(self, t: float, Y: Array) -> Array:
        """Q (N, n) at time t and states Y (2N, n)."""
        u = self.inputs(t)
        if u.ndim == 1:
            u = u[:, None]
        arguments = self._arguments
        if arguments is None or arguments.shape != (len(Y) + len(u), Y.shape[1]):
            arguments = self._arguments = np.empty((len(Y) + len(u), Y.shape[1]))
        arguments[:len(Y)] = Y
        arguments[len(Y):] = u
        values = self.stack(arguments)
        return self.scatter @ (values if self.shared else values * self.weight)


class Motion:
    """Lagrange's equations at fixed weights, for many states at once.

    A state array Y holds the variables on its first axis: rows q_1..q_N, v_1..v_N (and,
    with `drained`, the energy drained by the damping); its columns are the states
    (trajectories, or copies of segments). Made by `Dynamics.at`.

    What keeps the calls cheap (each runs once per integrator stage):
    - everything the equations need comes from one compiled call (`Func.stack`), the
      parts weighed state by state inside it when the weights are per state
      (`Stack.combined`: a polynomial's coefficients are weighed once, not its
      values at every call);
    - a constant mass matrix is inverted once and folded into the forces, so that the
      call returns the accelerations themselves (unless velocity-dependent forces must be
      added first: then its inverse is applied by a product and a sum over (N, N, n),
      much faster than einsum over n);
    - a changing mass matrix is solved by division (N = 1), Cramer's rule (N = 2, where a
      batched LU costs far more) or LU.
    """

    def __init__(self, terms: _Terms, weights: Array | None, forces: _Forces | None,
                 drained: bool, driven: _InputForces | None = None):
        self.n = terms.n
        self.rows = 2 * terms.n + bool(drained)
        self.drained = drained
        self.constant_mass = terms.constant_mass
        self._terms, self._weights, self._forces = terms, weights, forces
        self._driven = driven
        self._folded = False
        self._inverse: Array | None = None   # (N, N) shared, or (N, N, n) per state
        stack = self._invert_constant_mass() if terms.constant_mass else None
        if stack is None:
            stack = terms.full_stack if weights is None else self._weighted(terms.full_stack)
        self._values = stack

    def _invert_constant_mass(self) -> Callable[[Array], Array] | None:
        """Invert a constant mass matrix once; the stack that goes with the inverse."""
        N, terms, weights = self.n, self._terms, self._weights
        M = self.mass_matrix(np.zeros((2 * N, 1 if weights is None else weights.shape[1])))
        try:
            inverse = np.linalg.inv(M)
        except np.linalg.LinAlgError:
            # a singular one is no kinetic energy: left to the general path, where the
            # simulator's check names it before any step and the refinement's solve fails
            return None
        if weights is None:
            # (dM/dq) v vanishes, and M^-1 dL/dq are the accelerations
            self._inverse = inverse[0]
            self._folded = True
            return Func.stack([Func.combine(terms.forces[0][:N], [float(x) for x in row])
                               for row in self._inverse])
        self._inverse = inverse.transpose(1, 2, 0).copy()
        if terms.mixed:   # added to the forces before the inverse applies
            return self._weighted(terms.force_stack)
        self._folded = True
        return self._weighted(terms.force_stack, self._inverse)

    def _weighted(self, stack: Stack, mix: Array | None = None) -> Callable[[Array], Array]:
        """The stack's values (F of each part, part after part) summed with each state's
        weights, then mixed by `mix` (G, F, n) when given: a callable of the states
        (2N, n) returning (F or G, n)."""
        W = self._weights
        assert W is not None
        P, n = W.shape
        F = stack.n_funcs // P
        if mix is None:
            mix = np.broadcast_to(np.eye(F)[..., None], (F, F, n))
        K = mix[:, None] * W[None, :, None]                  # (G, P, F, n)
        return stack.combined(K.reshape(len(mix), P * F, n))

    def _apply_inverse(self, x: Array) -> Array:
        """The constant mass matrix's inverse times x (N, n)."""
        assert self._inverse is not None
        if self._inverse.ndim == 2:
            return self._inverse @ x
        return (self._inverse * x).sum(axis=1)

    def mass_matrix(self, Y: Array) -> Array:
        """M at states Y, shape (2N, ...) -> (..., N, N)."""
        stack = self._terms.mass_stack
        values = stack(Y) if self._weights is None else self._weighted(stack)(Y)
        return _assemble(values, self._terms.upper, self.n)

    def accelerations(self, Y: Array, t: float = 0.0) -> Array:
        """a (N, n) at states Y (2N, n) (and time t, for a driven model's inputs)."""
        N = self.n
        out = np.empty((N, Y.shape[1]))
        dissipative = self._forces(Y[:2 * N]) if self._forces else None
        self._accelerations(Y[:2 * N], self._with_inputs(t, Y[:2 * N], dissipative), out)
        return out

    def _with_inputs(self, t: float, Y: Array, forces: Array | None) -> Array | None:
        """The dissipative `forces` (N, n) with the inputs' generalized force added."""
        if self._driven is None:
            return forces
        driven = self._driven(t, Y)
        return driven if forces is None else forces + driven

    def _accelerations(self, Y: Array, forces: Array | None, out: Array) -> None:
        values = self._values(Y)
        if self._folded:
            if forces is None:
                out[:] = values
            else:
                np.add(values, self._apply_inverse(forces), out=out)
            return
        N, mixed = self.n, self._terms.mixed
        rhs = values[:N]
        V = Y[N:]
        for m, (i, k) in enumerate(mixed):
            rhs[i] -= values[N + m] * V[k]
        if forces is not None:
            rhs += forces
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
        V = Y[N:2 * N]
        dissipative = self._forces(Y[:2 * N]) if self._forces else None
        forces = self._with_inputs(t, Y[:2 * N], dissipative)
        out = np.empty_like(Y)
        out[:N] = V
        if self._folded and forces is None:   # the values are the accelerations: no call more
            out[N:2 * N] = self._values(Y[:2 * N])
        else:
            self._accelerations(Y[:2 * N], forces, out[N:2 * N])
        if self.drained:   # the energy's balance: drained by damping, supplied by inputs
            out[2 * N] = 0.0 if forces is None else -np.einsum("ij,ij->j", forces, V)
        return out.ravel()


def _assemble(upper: Array, order: Sequence[tuple[int, int]], N: int) -> Array:
    """Symmetric matrices (..., N, N) from their upper-triangle entries (len(order), ...)."""
    M = np.empty((*upper.shape[1:], N, N))
    for (i, j), entry in zip(order, upper, strict=True):
        M[..., i, j] = M[..., j, i] = entry
    return M
