"""Models: coordinates, velocities, parameters and an energy linear in the parameters.

A model is built once from its energy text; everything the fit and the simulator need
(the energy basis, the Lagrangian split E = T + V and its gradients) is derived from that
one expression, never written by hand per model.
"""

from __future__ import annotations

import dataclasses
import itertools
import keyword
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.errors import ModelError, UsageError
from hamid.model import expressions, parsing
from hamid.model.dissipation import Dissipation, shorthand_names
from hamid.model.forcing import Forcing, parse_forcing
from hamid.model.names import acceleration_name
from hamid.model.toml_values import check_keys, number, table

__all__ = ["BUILTINS", "Lagrangian", "Model", "builtin_model", "damping_table", "forcing_table",
           "model_from_info", "model_from_spec"]

BUILTINS: dict[str, dict[str, Any]] = {
    "peng-quadratic": {
        "description": "Peng & Peng (2007): two coupled oscillators with quadratic forces",
        "coordinates": ("u1", "u2"),
        "velocities": ("v1", "v2"),
        "energy": "(v1**2 + v2**2)/2 + w1sq*u1**2/2 + w2sq*u2**2/2 - a1*u1**3/3"
                  " - a2*u1**2*u2/2 - a3*u1*u2**2 - a6*u2**3/3",
        "parameters": ("w1sq", "w2sq", "a1", "a2", "a3", "a6"),
    },
    "duffing": {
        "description": "Duffing oscillator with cubic stiffness",
        "coordinates": ("x",),
        "velocities": ("v",),
        "energy": "v**2/2 + k*x**2/2 + k3*x**4/4",
        "parameters": ("k", "k3"),
    },
    "henon-heiles": {
        "description": "Henon-Heiles system (classic values a=b=c=1, d=-1/3)",
        "coordinates": ("x", "y"),
        "velocities": ("vx", "vy"),
        "energy": "(vx**2 + vy**2)/2 + a*x**2/2 + b*y**2/2 + c*x**2*y + d*y**3",
        "parameters": ("a", "b", "c", "d"),
    },
}
POLY_HELP = "poly:N:D"

_POLY_LIMIT = 200  # monomials; beyond this a fit would need more data than anyone records


@dataclass(frozen=True, eq=False)
class Lagrangian:
    """L = T - V of a natural energy, split like the energy: L = L0 + sum_k theta_k L_k."""

    L0: expressions.Func
    L: tuple[expressions.Func, ...]
    coordinates: tuple[str, ...]
    velocities: tuple[str, ...]

    @cached_property
    def _gradients(self) -> tuple[list[list[expressions.Func]], list[list[expressions.Func]]]:
        parts = (self.L0, *self.L)
        dv = [[f.diff(v) for v in self.velocities] for f in parts]
        dq = [[f.diff(q) for q in self.coordinates] for f in parts]
        return dv, dq

    def gradients(self, X: npt.NDArray[np.float64]) -> tuple[np.ndarray, np.ndarray]:
        """dL/dv and dL/dq of each part at the states X.

        Returns
        -------
        dLdv, dLdq : ndarray, shape (n_samples, n_coordinates, 1 + n_parameters)
            Index 0 of the last axis is the parameter-free part L0, then one per parameter.
        """
        n, N, parts = len(X), len(self.coordinates), 1 + len(self.L)
        values = self._gradient_stack(np.asarray(X, dtype=np.float64).T)
        # rows of the stack: (dv or dq, part, coordinate)
        both = values.reshape(2, parts, N, n).transpose(0, 3, 2, 1)
        return both[0], both[1]

    @cached_property
    def _gradient_stack(self) -> Any:
        dv, dq = self._gradients
        return expressions.Func.stack([f for table in (dv, dq) for row in table for f in row])

    @cached_property
    def _second(self) -> tuple[list[list[list[expressions.Func]]], ...]:
        variables = self.coordinates + self.velocities
        dv, dq = self._gradients
        return tuple([[[f.diff(x) for x in variables] for f in row] for row in grads]
                     for grads in (dv, dq))

    def second_derivatives(self, X: npt.NDArray[np.float64],
                           theta: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """d(dL/dv_i)/dx_c and d(dL/dq_i)/dx_c of L(theta) at the states X.

        Returns
        -------
        d_dLdv, d_dLdq : ndarray, shape (n_samples, n_coordinates, n_variables)
        """
        weights = np.concatenate([[1.0], np.asarray(theta, dtype=np.float64)])
        return tuple(
            sum(w * np.stack([np.stack([f(X) for f in per_x], axis=-1) for per_x in part],
                             axis=1)
                for w, part in zip(weights, table, strict=True) if w != 0.0)
            for table in self._second)


@dataclass(frozen=True, eq=False)
class Model:
    """An energy E(x; theta) = E0(x) + sum_k theta_k phi_k(x), x = (coordinates, velocities)."""

    name: str
    energy: str
    coordinates: tuple[str, ...]
    velocities: tuple[str, ...]
    parameters: tuple[str, ...]
    E0: expressions.Func
    phi: tuple[expressions.Func, ...]
    description: str = ""
    dissipation: Dissipation | None = None   # the model file's [damping] function
    forcing: Forcing | None = None   # the model file's [forcing]: recorded inputs, their work
    # the names of the coordinates' accelerations (`[model] accelerations`); () for the
    # defaults, which follow the velocities' names (`acceleration_name`)
    accelerations: tuple[str, ...] = ()

    @property
    def energy_parameters(self) -> tuple[str, ...]:
        """The parameters of the energy (a forcing's gains follow them in `parameters`)."""
        gains = self.forcing.gains if self.forcing is not None else ()
        return self.parameters[:len(self.parameters) - len(gains)]

    @property
    def inputs(self) -> tuple[str, ...]:
        """The recorded inputs of a driven model (columns of its recordings); none if free."""
        return self.forcing.inputs if self.forcing is not None else ()

    @property
    def variables(self) -> tuple[str, ...]:
        return self.coordinates + self.velocities

    @property
    def acceleration_names(self) -> tuple[str, ...]:
        """The name of each coordinate's acceleration: the model file's, else the one that
        follows its velocity's (`acceleration_name`)."""
        return self.accelerations or tuple(map(acceleration_name, self.velocities))

    def dissipative(self, kinds: Sequence[str] = ()) -> Dissipation:
        """The dissipation a fit takes: the model's own function plus the shorthand terms
        of `kinds` (``--damping``)."""
        own = self.dissipation or Dissipation(self.coordinates, self.velocities)
        return own.with_kinds(kinds)

    @property
    def is_polynomial(self) -> bool:
        return isinstance(self.E0, expressions.Polynomial)

    def energy_basis(self, X: npt.NDArray[np.float64]) -> tuple[np.ndarray, np.ndarray]:
        """E0 and the basis functions at the states X, shape (n, 2N).

        Returns
        -------
        E0 : ndarray, shape (n,)
        Phi : ndarray, shape (n, n_parameters)
        """
        values = self._energy_terms(np.asarray(X, dtype=np.float64).T)
        return values[0], values[1:].T

    @cached_property
    def _energy_terms(self) -> Any:
        """E0 and every phi_k evaluated together (their monomials shared)."""
        return expressions.Func.stack([self.E0, *self.phi])

    def total_energy(self, X: npt.NDArray[np.float64], theta: Sequence[float]) -> np.ndarray:
        """E(x; theta) at the states X."""
        E0, Phi = self.energy_basis(X)
        return E0 + Phi @ np.asarray(theta, dtype=np.float64)

    @cached_property
    def _energy_gradient(self) -> list[list[expressions.Func]]:
        return [[f.diff(x) for x in self.variables] for f in (self.E0, *self.phi)]

    def energy_gradient(self, X: npt.NDArray[np.float64],
                        theta: Sequence[float]) -> np.ndarray:
        """dE/dx at the states X, shape (n_samples, n_variables)."""
        weights = np.concatenate([[1.0], np.asarray(theta, dtype=np.float64)])
        return sum(w * np.stack([f(X) for f in row], axis=-1)
                   for w, row in zip(weights, self._energy_gradient, strict=True) if w != 0.0)

    @cached_property
    def _natural(self) -> Lagrangian | str:
        parts = (self.E0, *self.phi)
        labels = ("the parameter-free part", *(f"the term of {p!r}" for p in self.parameters))
        lagrangians = []
        for f, label in zip(parts, labels, strict=True):
            degrees = f.velocity_degrees(self.velocities)
            if degrees is None or set(degrees) - {0, 2}:
                bad = [f] if degrees is None else [g for d, g in degrees.items()
                                                   if d not in (0, 2)]
                text = " + ".join(g.text() if isinstance(g, expressions.Polynomial)
                                  else str(g.expression) for g in bad)
                return (f"{label} of the energy is not a kinetic energy quadratic in the "
                        f"velocities plus a potential energy: {text!r}")
            T, V = degrees.get(2), degrees.get(0)
            present = [(g, w) for g, w in ((T, 1.0), (V, -1.0)) if g is not None]
            lagrangians.append(expressions.Func.combine([g for g, _ in present],
                                                 [w for _, w in present]) if present else f)
        return Lagrangian(lagrangians[0], tuple(lagrangians[1:]), self.coordinates,
                          self.velocities)

    @cached_property
    def kinks(self) -> tuple[expressions.Func, ...]:
        """Functions of the state whose zeros the energy is not smooth at (abs, sign,
        fractional powers); none for a polynomial."""
        if self.is_polynomial:
            return ()
        tree = parsing.parse(self.energy, None)
        return tuple(expressions.kinks(parsing.to_sympy(tree), self.variables))

    @property
    def is_natural(self) -> bool:
        """Whether E = T + V with T quadratic in the velocities (Lagrange's equations apply)."""
        return isinstance(self._natural, Lagrangian)

    @cached_property
    def per_unit_mass(self) -> bool:
        """Whether the energy has a kinetic part (quadratic in the velocities) and no
        parameter's term has one: the energy and its parameters are then per unit mass."""
        if not self.is_natural:
            return False
        kinetic = [f.velocity_degrees(self.velocities) or {} for f in (self.E0, *self.phi)]
        return 2 in kinetic[0] and not any(2 in degrees for degrees in kinetic[1:])

    @property
    def lagrangian(self) -> Lagrangian:
        """The Lagrangian split; raises ModelError for an energy that is not natural."""
        if isinstance(self._natural, str):
            raise ModelError(f"model {self.name!r}: {self._natural}")
        return self._natural

    def info(self) -> dict[str, Any]:
        """The plain description stored in result files and data provenance."""
        own = self.dissipation
        return {"name": self.name, "energy": self.energy, "coordinates": list(self.coordinates),
                "velocities": list(self.velocities),
                **({"accelerations": list(self.accelerations)} if self.accelerations else {}),
                "parameters": list(self.energy_parameters),
                "dissipation": None if own is None else
                {"function": own.function, "parameters": list(own.parameters)},
                **({} if self.forcing is None else {"forcing": self.forcing.info()})}


def _check_names(coordinates: Sequence[str], velocities: Sequence[str],
                 parameters: Sequence[str] | None, where: str) -> None:
    if not coordinates:
        raise ModelError(f"{where}: 'coordinates' must list at least one name")
    if len(velocities) != len(coordinates):
        raise ModelError(f"{where}: {len(coordinates)} coordinates but {len(velocities)} "
                         "velocities; give one velocity per coordinate")
    names = [*coordinates, *velocities, *(parameters or ())]
    for name in names:
        if (not isinstance(name, str) or not name.isidentifier() or not name.isascii()
                or keyword.iskeyword(name) or name in parsing.FUNCTIONS
                or name in parsing.CONSTANTS):
            raise ModelError(f"{where}: {name!r} cannot be used as a name")
    for name, count in _counts(names).items():
        if count > 1:
            raise ModelError(f"{where}: the name {name!r} is declared more than once")


def _counts(names: Sequence[str]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for name in names:
        counts[name] = counts.get(name, 0) + 1
    return counts


def model_from_expression(name: str, energy: str, coordinates: Sequence[str],
                          velocities: Sequence[str], parameters: Sequence[str] | None = None,
                          *, description: str = "", where: str = "model") -> Model:
    """Build a model from its energy text; parameters default to every other symbol."""
    coordinates, velocities = tuple(coordinates), tuple(velocities)
    _check_names(coordinates, velocities, parameters, where)
    allowed = None if parameters is None else [*coordinates, *velocities, *parameters]
    tree = parsing.parse(energy, allowed, where=f"{where}: energy")
    if parameters is None:
        parameters = [s for s in parsing.symbols_in_order(tree)
                      if s not in coordinates and s not in velocities]
        _check_names(coordinates, velocities, parameters, where)
    if not parameters:
        raise ModelError(f"{where}: the energy has no parameters to fit")
    E0, phi = parsing.split_linear(tree, coordinates + velocities, tuple(parameters),
                                   where=f"{where}: energy")
    return Model(name=name, energy=energy, coordinates=coordinates, velocities=velocities,
                 parameters=tuple(parameters), E0=E0, phi=phi, description=description)


@lru_cache(maxsize=32)
class UnknownModelError(ModelError, UsageError):
    """A model name that is neither built in nor a file: a usage error (exit status 2)."""


def builtin_model(name: str) -> Model:
    """A built-in model by name, or the polynomial family ``poly:N:D``."""
    if name.startswith("poly:"):
        return _poly_model(name)
    if name not in BUILTINS:
        import difflib

        close = difflib.get_close_matches(name.lower(), list(BUILTINS), n=1, cutoff=0.6)
        if not close and os.path.isfile(name + ".toml"):
            close = [name + ".toml"]
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise UnknownModelError(f"unknown model {name!r}; built-in models: "
                                f"{', '.join([*BUILTINS, POLY_HELP])}, or a TOML model "
                                f"file{hint}")
    spec = BUILTINS[name]
    return model_from_expression(name, spec["energy"], spec["coordinates"],
                                 spec["velocities"], spec["parameters"],
                                 description=spec["description"], where=f"model {name!r}")


def poly_spec(n_coordinates: int, degree: int,
              coordinates: Sequence[str] | None = None,
              velocities: Sequence[str] | None = None) -> dict[str, Any]:
    """The energy of ``poly:N:D``: unit kinetic energy, one parameter per monomial.

    The monomials are counted before any is built: a name such as poly:200000:2 would
    otherwise take minutes and gigabytes before being refused.
    """
    count = math.comb(n_coordinates + degree, degree) - 1 - n_coordinates
    if count > _POLY_LIMIT:
        shown = f"{count:,}" if count < 10**15 else f"about 10^{len(str(count)) - 1}"
        raise ModelError(f"poly:{n_coordinates}:{degree} has {shown} terms (at most "
                         f"{_POLY_LIMIT}); use a lower degree, fewer coordinates or a model "
                         "file")
    coordinates = list(coordinates or [f"q{i + 1}" for i in range(n_coordinates)])
    velocities = list(velocities or [f"v{i + 1}" for i in range(n_coordinates)])
    monomials = [e for d in range(2, degree + 1) for e in _exponents(n_coordinates, d)]
    parameters = ["c_" + "_".join(map(str, e)) for e in monomials]
    kinetic = " + ".join(f"{v}**2/2" for v in velocities)
    potential = " + ".join(
        "*".join([p, *(q if k == 1 else f"{q}**{k}"
                       for q, k in zip(coordinates, e, strict=True) if k)])
        for p, e in zip(parameters, monomials, strict=True))
    return {"description": f"polynomial potential of degree {degree} in {n_coordinates} "
                           "coordinates, unit masses",
            "coordinates": tuple(coordinates), "velocities": tuple(velocities),
            "energy": f"{kinetic} + {potential}", "parameters": tuple(parameters)}


def _exponents(n: int, degree: int) -> list[tuple[int, ...]]:
    """Exponent tuples of total `degree` in n variables, highest power of q1 first."""
    combos = itertools.combinations_with_replacement(range(n), degree)
    return sorted({tuple(c.count(i) for i in range(n)) for c in combos}, reverse=True)


def parse_poly_name(name: str) -> tuple[int, int]:
    """N and D of a ``poly:N:D`` name."""
    parts = name.split(":")
    try:
        n, d = int(parts[1]), int(parts[2])
        if len(parts) != 3 or n < 1 or d < 2:
            raise ValueError
    except (ValueError, IndexError) as exc:
        raise ModelError(f"model {name!r}: expected poly:N:D with N >= 1 coordinates and "
                         "degree D >= 2, e.g. poly:2:3") from exc
    return n, d


def _poly_model(name: str, coordinates: Sequence[str] | None = None,
                velocities: Sequence[str] | None = None) -> Model:
    n, d = parse_poly_name(name)
    spec = poly_spec(n, d, coordinates, velocities)
    return model_from_expression(name, spec["energy"], spec["coordinates"],
                                 spec["velocities"], spec["parameters"],
                                 description=spec["description"], where=f"model {name!r}")


def poly_model_over(coordinates: Sequence[str], velocities: Sequence[str],
                    degree: int = 3) -> Model:
    """``poly:N:D`` over named columns, for data that come without a model."""
    return _poly_model(f"poly:{len(coordinates)}:{degree}", coordinates, velocities)


_MODEL_KEYS = ("builtin", "name", "coordinates", "velocities", "accelerations", "energy",
               "parameters")


def model_from_spec(spec: Mapping[str, Any], *, where: str = "[model]") -> Model:
    """A model from the ``[model]`` table of a TOML file (builtin name or expression)."""
    check_keys(spec, _MODEL_KEYS, where=where)
    if "builtin" in spec:
        extra = [k for k in spec if k not in ("builtin",)]
        if extra:
            raise ModelError(f"{where}: 'builtin' cannot be combined with {', '.join(extra)}")
        if not isinstance(spec["builtin"], str):
            raise ModelError(f"{where}: 'builtin' must be a model name")
        return builtin_model(spec["builtin"])
    for key in ("coordinates", "velocities", "energy"):
        if key not in spec:
            raise ModelError(f"{where}: missing key {key!r} (or give 'builtin')")
    _check_lists(spec, where)
    if not isinstance(spec["energy"], str):
        raise ModelError(f"{where}: 'energy' must be a string")
    name = spec.get("name", "custom")
    if not isinstance(name, str):
        raise ModelError(f"{where}: 'name' must be a string")
    model = model_from_expression(name, spec["energy"], spec["coordinates"],
                                  spec["velocities"], spec.get("parameters"), where=where)
    return _with_accelerations(model, spec.get("accelerations"), where)


def _with_accelerations(model: Model, names: Sequence[str] | None, where: str) -> Model:
    """The model with the accelerations' names of its description, one per coordinate,
    none a name of the model already."""
    if not names:
        return model
    if len(names) != len(model.coordinates):
        raise ModelError(f"{where}: {len(model.coordinates)} coordinates but {len(names)} "
                         "accelerations; give one acceleration per coordinate")
    taken = {*model.variables, *model.parameters}
    for name in names:
        if not name.isidentifier() or name in taken:
            raise ModelError(f"{where}: acceleration name {name!r} is not a new name")
        taken.add(name)
    return dataclasses.replace(model, accelerations=tuple(names))


def _check_lists(spec: Mapping[str, Any], where: str) -> None:
    """Helper: the names of a model's description are lists of text (a string "theta"
    would be read as the names t, h, e, t, a)."""
    for key in ("coordinates", "velocities", "accelerations", "parameters"):
        value = spec.get(key)
        if value is not None and not (isinstance(value, list)
                                      and all(isinstance(v, str) for v in value)):
            found = f", not the string {value[:40]!r}" if isinstance(value, str) else ""
            raise ModelError(f"{where}: {key!r} must be a list of names{found}")


_MODEL_FILE_KEYS = ("model", "parameters", "initial", "simulate", "noise", "damping",
                    "forcing")


def load_model(name_or_path: str | os.PathLike[str]) -> Model:
    """A built-in model by name (``duffing``, ``poly:2:3``, ...) or the model of a TOML file.

    Examples
    --------
    >>> hamid.load_model("duffing").parameters
    ('k', 'k3')
    """
    text = os.fspath(name_or_path)
    if os.path.isdir(text):
        raise ModelError(f"{text}: is a folder, not a file")
    if not text.endswith(".toml"):
        return builtin_model(text)
    from hamid.data import documents
    from hamid.model.toml_values import check_keys

    document = documents.read_toml(text)
    check_keys(document, _MODEL_FILE_KEYS, where=text)
    if "model" not in document:
        raise ModelError(f"{text}: no [model] table")
    model = model_from_spec(document["model"], where=f"{text}: [model]")
    if "forcing" in document:
        model = forcing_table(model, document["forcing"], where=f"{text}: [forcing]")
    return damping_table(model, document.get("damping", {}), where=f"{text}: [damping]")[0]


def model_from_info(info: Mapping[str, Any], *, where: str) -> Model:
    """The model a report or a simulated file records (`Model.info`), with its
    dissipation function."""
    _check_lists(info, where)
    model = model_from_expression(str(info.get("name") or "custom"), info["energy"],
                                  info["coordinates"], info["velocities"],
                                  info.get("parameters"), where=where)
    model = _with_accelerations(model, info.get("accelerations"), where)
    if info.get("forcing"):
        model = forcing_table(model, info["forcing"], where=where)
    own = info.get("dissipation")
    if not own:
        return model
    return damping_table(model, {"dissipation": own["function"],
                                 "parameters": own["parameters"]}, where=where)[0]


def forcing_table(model: Model, value: Any, *, where: str = "[forcing]") -> Model:
    """The model with the forcing of a ``[forcing]`` table (`hamid.model.forcing`): its
    inputs and work, and its gains appended to the parameters, with no part in the
    energy."""
    forcing = parse_forcing(value, coordinates=model.coordinates, velocities=model.velocities,
                            parameters=model.parameters, where=where)
    zero = expressions.Func.combine([model.E0], [0.0])
    return dataclasses.replace(model, parameters=forcing.parameters,
                               phi=(*model.phi, *(zero for _ in forcing.gains)),
                               forcing=forcing)


def damping_table(model: Model, value: Any, *,
                  where: str = "[damping]") -> tuple[Model, dict[str, float]]:
    """The model with the dissipation function of a ``[damping]`` table, and the table's
    coefficient values (a simulation's; a fit ignores them).

    The table may hold ``dissipation`` (Rayleigh's R, `hamid.model.dissipation`) with its
    ``parameters`` (default: every symbol that is not a state variable), and a value for
    any coefficient: those of R, and the shorthand ``c_<q>``, ``mu_<q>``, ``d_<q>``.
    """
    entries = table(value, where=where)
    dissipation = None
    if "dissipation" in entries:
        function = entries["dissipation"]
        if not isinstance(function, str):
            raise ModelError(f"{where}: 'dissipation' must be a string")
        names = entries.get("parameters")
        if names is None:
            names = [s for s in parsing.symbols_in_order(parsing.parse(
                         function, None, where=f"{where}: dissipation"))
                     if s not in model.variables]
        if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
            raise ModelError(f"{where}: 'parameters' must be a list of names")
        _check_names(model.coordinates, model.velocities, [*model.parameters, *names], where)
        dissipation = Dissipation.build(model.coordinates, model.velocities, function=function,
                                        parameters=names, where=where)
    elif "parameters" in entries:
        raise ModelError(f"{where}: 'parameters' without a 'dissipation' function")
    own = dissipation.names if dissipation is not None else ()
    check_keys(entries, ("dissipation", "parameters", *own, *shorthand_names(model.coordinates)),
               where=where)
    values = {k: number(v, where=f"{where} {k}", non_negative=True)
              for k, v in entries.items() if k not in ("dissipation", "parameters")}
    if dissipation is None:
        return model, values
    return dataclasses.replace(model, dissipation=dissipation), values
