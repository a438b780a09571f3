"""The candidate terms of a model selection: one per parameter of a library model, written
in the model's own syntax, ordered by simplicity, and the model of any subset of them as
an energy text and a TOML model file (docs/method.md, "Model selection").
"""

from __future__ import annotations

import ast
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

from hamid.errors import UsageError
from hamid.model import expressions
from hamid.model.models import Model, model_from_expression

__all__ = ["Library", "Term"]


@dataclass(frozen=True)
class Term:
    """One candidate term: its parameter, its expression, and how simple it is.

    complexity : (degree, monomials, variables) of a polynomial term; a term that is not a
        polynomial in the coordinates and velocities comes after every polynomial one.
    """

    parameter: str
    text: str
    complexity: tuple[float, ...]


@dataclass(frozen=True)
class Library:
    """The terms of a library model, each with its own parameter."""

    model: Model
    terms: tuple[Term, ...]
    # the energy text's top-level terms: "" -> the parameter-free ones, parameter -> its
    # own with the parameter; None when some term holds several parameters
    parts: dict[str, list[tuple[int, ast.expr]]] | None = None

    @classmethod
    def of(cls, model: Model) -> Library:
        """Every parameter of `model` as a candidate term, written as in its energy text
        (``a2*(theta - pi)**2`` gives ``(theta - pi)**2``) where the text has one
        parameter per term, else as the expanded function."""
        parts = _parts(model.energy, model.parameters)
        return cls(model, tuple(
            Term(p, _join(parts[p]) if parts and p in parts else _text(f),
                 _complexity(f, model.variables))
            for p, f in zip(model.parameters, model.phi, strict=True)), parts)

    @property
    def name(self) -> str:
        return self.model.name

    def texts(self, indices: Sequence[int]) -> list[str]:
        """The expressions of the terms at `indices`, in library order."""
        return [self.terms[k].text for k in sorted(indices)]

    def find(self, items: Sequence[str], option: str = "--keep") -> list[int]:
        """Positions of terms given by expression (``u1**2``) or by parameter name."""
        spaced = {_squeezed(t.text): k for k, t in enumerate(self.terms)}
        named = {t.parameter: k for k, t in enumerate(self.terms)}
        found = []
        for item in items:
            k = named.get(item.strip(), spaced.get(_squeezed(item)))
            if k is None:
                raise UsageError(f"{option}: {item!r} is not a term of the library "
                                 f"{self.name} (its terms: "
                                 f"{', '.join(t.text for t in self.terms)})")
            found.append(k)
        return sorted(set(found))

    def submodel(self, indices: Sequence[int], name: str) -> Model:
        """The model with the terms at `indices` only, their parameters as in the library."""
        return model_from_expression(name, self.energy(indices), self.model.coordinates,
                                     self.model.velocities,
                                     [self.terms[k].parameter for k in sorted(indices)],
                                     description=f"terms of {self.name} chosen by hamid select")

    def energy(self, indices: Sequence[int]) -> str:
        """The energy text of the terms at `indices` with the parameter-free part, in the
        words of the library's energy where it has one parameter per term."""
        chosen = [self.terms[k].parameter for k in sorted(indices)]
        if self.parts is not None:
            return _join([item for key in ("", *chosen) for item in self.whole[key]])
        return " + ".join([_text(self.model.E0),
                           *(_product(p, self.terms[k].text)
                             for p, k in zip(chosen, sorted(indices), strict=True))])

    @property
    def whole(self) -> dict[str, list[tuple[int, ast.expr]]]:
        """The top-level terms of the energy text, parameters included."""
        return _parts(self.model.energy, self.model.parameters, strip=False) or {}

    def toml(self, indices: Sequence[int], name: str, comments: Sequence[str]) -> str:
        """A model file of the terms at `indices`, as `hamid fit --model` reads it."""
        m = self.model
        # a comment ends at a line break: any in the text (a model's name) is escaped
        lines = [*(f"# {line.encode('unicode_escape').decode('ascii')}" for line in comments),
                 "[model]",
                 f"name = {_string(name)}",
                 f"coordinates = [{', '.join(map(_string, m.coordinates))}]",
                 f"velocities = [{', '.join(map(_string, m.velocities))}]",
                 f"energy = {_string(self.energy(indices))}",
                 "parameters = [" + ", ".join(_string(self.terms[k].parameter)
                                              for k in sorted(indices)) + "]"]
        return "\n".join(lines) + "\n"


def _parts(energy: str, parameters: Sequence[str], *,
           strip: bool = True) -> dict[str, list[tuple[int, ast.expr]]] | None:
    """The energy text's top-level terms with their signs, by parameter ("" for those
    without one); with `strip`, each term with its parameter factor taken out. None when a
    term holds several parameters or one that is not a plain factor."""
    found: dict[str, list[tuple[int, ast.expr]]] = {"": []}

    def visit(node: ast.expr, sign: int) -> bool:
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add | ast.Sub):
            return visit(node.left, sign) and visit(
                node.right, sign if isinstance(node.op, ast.Add) else -sign)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
            return visit(node.operand, -sign if isinstance(node.op, ast.USub) else sign)
        names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)} & set(parameters)
        if len(names) > 1:
            return False
        key = names.pop() if names else ""
        term = _without(node, key) if key and strip else node
        found.setdefault(key, []).append((sign, term))
        return term is not None

    return found if visit(ast.parse(energy, mode="eval").body, 1) else None


def _without(node: ast.expr, name: str) -> ast.expr | None:
    """A product with the factor `name` taken out, or None if it is not a plain factor."""
    if isinstance(node, ast.Name) and node.id == name:
        return ast.Constant(1)
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult | ast.Div):
        has = [any(isinstance(n, ast.Name) and n.id == name for n in ast.walk(side))
               for side in (node.left, node.right)]
        if isinstance(node.op, ast.Mult) and has[1]:
            if isinstance(node.right, ast.Name):
                return node.left
            inner = _without(node.right, name)
            return None if inner is None else ast.BinOp(node.left, ast.Mult(), inner)
        if has[0]:
            if isinstance(node.op, ast.Mult) and isinstance(node.left, ast.Name):
                return node.right
            inner = _without(node.left, name)
            return None if inner is None else ast.BinOp(inner, node.op, node.right)
    return None


def _join(items: Sequence[tuple[int, ast.expr]]) -> str:
    """Signed terms as one expression, written compactly (``u1*u2**2``, ``x - pi``)."""
    total: ast.expr | None = None
    for sign, node in items:
        if total is None:
            total = node if sign > 0 else ast.UnaryOp(ast.USub(), node)
        else:
            total = ast.BinOp(total, ast.Add() if sign > 0 else ast.Sub(), node)
    if total is None:
        return "0"
    # -(u1**3/3) is -u1**3/3: unary minus binds tighter than * and / alone
    lead = isinstance(total, ast.UnaryOp) and isinstance(total.operand, ast.BinOp) and \
        isinstance(total.operand.op, ast.Mult | ast.Div)
    text = "-" + ast.unparse(total.operand) if lead else ast.unparse(total)
    for op in ("**", "*", "/"):
        text = text.replace(f" {op} ", op)
    return text


def _string(text: str) -> str:
    """A TOML basic string (JSON's escapes are TOML's, for ASCII text)."""
    return json.dumps(text, ensure_ascii=True)


def _squeezed(text: str) -> str:
    return "".join(text.split())


def _text(f: expressions.Func) -> str:
    """A function as an expression that `hamid.model.parsing` parses back to the same
    function."""
    if isinstance(f, expressions.Polynomial):
        text = ""
        for row, c in zip(f.exponents, f.coefficients, strict=True):
            factors = [n if e == 1 else f"{n}**{e}"
                       for n, e in zip(f.variables, row, strict=True) if e]
            # repr: the shortest digits that read back as the same double
            body = "*".join(factors if abs(c) == 1.0 and factors
                            else [repr(float(abs(c))), *factors])
            sign = ("-" if c < 0 else "") if not text else (" - " if c < 0 else " + ")
            text += sign + body
        return text
    assert isinstance(f, expressions.Symbolic)
    return str(f.expression).replace("Abs(", "abs(")


def _product(parameter: str, text: str) -> str:
    """``parameter*text``, with the text in parentheses unless it is a single product."""
    node = ast.parse(text, mode="eval").body
    single = isinstance(node, ast.Name | ast.Call) or (
        isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult | ast.Div | ast.Pow))
    return f"{parameter}*{text}" if single else f"{parameter}*({text})"


def _complexity(f: expressions.Func, variables: Sequence[str]) -> tuple[float, ...]:
    """(degree, monomials, variables involved) of a polynomial term; a term that is not a
    polynomial gets an infinite degree and counts its operations instead."""
    if isinstance(f, expressions.Polynomial):
        return (float(f.exponents.sum(axis=1).max()), float(len(f.coefficients)),
                float((f.exponents.sum(axis=0) > 0).sum()))
    import sympy

    symbols = [sympy.Symbol(v, real=True) for v in variables]
    used = [s for s in symbols if f.expression.has(s)]
    try:
        poly = sympy.Poly(f.expression, *used)
    except sympy.PolynomialError:
        return (math.inf, float(sympy.count_ops(f.expression)), float(len(used)))
    return (float(poly.total_degree()), float(len(poly.terms())), float(len(used)))
