"""Law expressions: a whitelist grammar, exact symbolic derivatives, compiled numpy closures.

A law is a string such as ``"P20 * (1 + alpha * (T.sw - 20))"``. It is parsed by a small
recursive-descent parser (never ``eval``) into an immutable tree of :class:`Expr` nodes. The
grammar admits numbers, names (letters, digits, ``_`` and ``.``), ``+ - * / **``, parentheses and
the functions ``exp log sqrt tanh min max abs sign`` plus any lookup tables the model declares.
Derivatives are taken symbolically on the tree (with light constant folding) and every tree
compiles to a Python function over numpy arrays, so a law evaluates on whole time series at once.
A tree with operators compiles to generated straight-line code (one statement per node, a
subtree shared by the tree evaluated once): the service evaluates its laws on single values
every tick, where calling a closure per node cost more than the arithmetic.

>>> e = parse("2 * x ** 3 + exp(y)")
>>> str(e.diff("x"))
'(2 * (3 * x ** 2))'
>>> float(e.compile()({"x": 2.0, "y": 0.0}))
17.0
"""
from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ThermalEdgeError

Value = float | np.ndarray  # a scalar, or an array of values evaluated element-wise
Env = Mapping[str, Value]
Compiled = Callable[[Env], Value]
Table = Callable[..., np.ndarray]  # a model-declared lookup table (a ``tables.Lookup``)

FUNCTIONS_1 = {"exp": np.exp, "log": np.log, "sqrt": np.sqrt, "tanh": np.tanh, "abs": np.abs, "sign": np.sign}
FUNCTIONS_2 = {"min": np.minimum, "max": np.maximum}


class ExprError(ThermalEdgeError, ValueError):
    """A law that does not parse, names something unknown or cannot be differentiated."""


class Expr:
    """Base of the expression tree. Subclasses are frozen dataclasses."""

    def free(self) -> frozenset[str]:
        """Names this expression depends on."""
        raise NotImplementedError

    def diff(self, name: str) -> Expr:
        """Exact derivative with respect to ``name``."""
        raise NotImplementedError

    def compile(self) -> Compiled:
        """Closure evaluating the expression from a mapping of names to floats or arrays."""
        raise NotImplementedError

    def substitute(self, values: Mapping[str, Expr]) -> Expr:
        """Replace names by expressions (used to inline constants and derived inputs)."""
        raise NotImplementedError

    def is_const(self) -> bool:
        return isinstance(self, Num)

    # operator sugar used when building element laws in code
    def __add__(self, o: Expr | float) -> Expr:
        return add(self, as_expr(o))

    def __radd__(self, o: float) -> Expr:
        return add(as_expr(o), self)

    def __sub__(self, o: Expr | float) -> Expr:
        return sub(self, as_expr(o))

    def __mul__(self, o: Expr | float) -> Expr:
        return mul(self, as_expr(o))

    def __rmul__(self, o: float) -> Expr:
        return mul(as_expr(o), self)

    def __truediv__(self, o: Expr | float) -> Expr:
        return div(self, as_expr(o))

    def __rtruediv__(self, o: float) -> Expr:
        return div(as_expr(o), self)

    def __neg__(self) -> Expr:
        return neg(self)


@dataclass(frozen=True)
class Num(Expr):
    value: float

    def free(self) -> frozenset[str]:
        return frozenset()

    def diff(self, name: str) -> Expr:
        return ZERO

    def compile(self) -> Compiled:
        v = self.value
        return lambda env: v

    def substitute(self, values: Mapping[str, Expr]) -> Expr:
        return self

    def __str__(self) -> str:
        v = self.value
        return repr(int(v)) if v == int(v) and abs(v) < 1e15 else repr(v)


@dataclass(frozen=True)
class Name(Expr):
    name: str

    def free(self) -> frozenset[str]:
        return frozenset((self.name,))

    def diff(self, name: str) -> Expr:
        return ONE if name == self.name else ZERO

    def compile(self) -> Compiled:
        n = self.name
        return lambda env: env[n]

    def substitute(self, values: Mapping[str, Expr]) -> Expr:
        return values.get(self.name, self)

    def __str__(self) -> str:
        return self.name


@dataclass(frozen=True)
class Bin(Expr):
    op: str  # one of + - * / **
    a: Expr
    b: Expr

    def free(self) -> frozenset[str]:
        return self.a.free() | self.b.free()

    def diff(self, name: str) -> Expr:
        a, b = self.a, self.b
        if name not in self.free():
            return ZERO
        da, db = a.diff(name), b.diff(name)
        if self.op == "+":
            return add(da, db)
        if self.op == "-":
            return sub(da, db)
        if self.op == "*":
            return add(mul(da, b), mul(a, db))
        if self.op == "/":
            return sub(div(da, b), div(mul(a, db), mul(b, b)))
        # power: constant exponent is the common case and keeps the result defined at a <= 0
        if name not in b.free():
            return mul(mul(b, power(a, sub(b, ONE))), da)
        return mul(self, add(mul(db, call("log", a)), div(mul(b, da), a)))

    def compile(self) -> Compiled:
        return _generated([self], single=True)

    def substitute(self, values: Mapping[str, Expr]) -> Expr:
        return _bin(self.op, self.a.substitute(values), self.b.substitute(values))

    def __str__(self) -> str:
        return f"({self.a} {self.op} {self.b})" if self.op != "**" else f"{_atom(self.a)} ** {_atom(self.b)}"


@dataclass(frozen=True)
class Call(Expr):
    fn: str
    args: tuple[Expr, ...]
    table: Table | None = None  # a Lookup for model-declared tables, else None

    def free(self) -> frozenset[str]:
        out: frozenset[str] = frozenset()
        for a in self.args:
            out |= a.free()
        return out

    def diff(self, name: str) -> Expr:
        if name not in self.free():
            return ZERO
        a = self.args[0]
        da = a.diff(name)
        fn = self.fn
        if self.table is not None:
            raise ExprError(f"table {fn}() may depend only on inputs, not on {name!r}")
        if fn == "exp":
            return mul(self, da)
        if fn == "log":
            return div(da, a)
        if fn == "sqrt":
            return div(da, mul(Num(2.0), self))
        if fn == "tanh":
            return mul(sub(ONE, mul(self, self)), da)
        if fn == "abs":
            return mul(Call("sign", (a,)), da)
        if fn == "sign":
            return ZERO
        if fn in ("min", "max"):
            b = self.args[1]
            db = b.diff(name)
            # the derivative of the branch that is active (a one-sided choice at ties)
            pick_a = Call("step_ge" if fn == "max" else "step_le", (a, b))
            return add(mul(pick_a, da), mul(sub(ONE, pick_a), db))
        if fn in ("step_ge", "step_le"):
            return ZERO
        raise ExprError(f"cannot differentiate {fn}()")

    def compile(self) -> Compiled:
        return _generated([self], single=True)

    def substitute(self, values: Mapping[str, Expr]) -> Expr:
        return call(self.fn, *[a.substitute(values) for a in self.args], table=self.table)

    def __str__(self) -> str:
        return f"{self.fn}({', '.join(str(a) for a in self.args)})"


ZERO, ONE = Num(0.0), Num(1.0)


def as_expr(x: Expr | float | int | str) -> Expr:
    """Numbers become :class:`Num`, strings are parsed, expressions pass through."""
    if isinstance(x, Expr):
        return x
    if isinstance(x, str):
        return parse(x)
    return Num(float(x))


def _atom(e: Expr) -> str:
    return str(e) if isinstance(e, (Num, Name, Call)) and not (isinstance(e, Num) and e.value < 0) else f"({e})"


def _bin(op: str, a: Expr, b: Expr) -> Expr:
    return {"+": add, "-": sub, "*": mul, "/": div, "**": power}[op](a, b)


def add(a: Expr, b: Expr) -> Expr:
    if isinstance(a, Num) and isinstance(b, Num):
        return Num(a.value + b.value)
    if a == ZERO:
        return b
    if b == ZERO:
        return a
    return Bin("+", a, b)


def sub(a: Expr, b: Expr) -> Expr:
    if isinstance(a, Num) and isinstance(b, Num):
        return Num(a.value - b.value)
    if b == ZERO:
        return a
    if a == ZERO:
        return neg(b)
    return Bin("-", a, b)


def neg(a: Expr) -> Expr:
    if isinstance(a, Num):
        return Num(-a.value)
    return Bin("*", Num(-1.0), a)


def mul(a: Expr, b: Expr) -> Expr:
    if isinstance(a, Num) and isinstance(b, Num):
        return Num(a.value * b.value)
    if a == ZERO or b == ZERO:
        return ZERO
    if a == ONE:
        return b
    if b == ONE:
        return a
    return Bin("*", a, b)


def div(a: Expr, b: Expr) -> Expr:
    if isinstance(b, Num) and b.value == 0.0:
        raise ExprError("division by the constant zero")
    if isinstance(a, Num) and isinstance(b, Num):
        return Num(a.value / b.value)
    if a == ZERO:
        return ZERO
    if b == ONE:
        return a
    return Bin("/", a, b)


def power(a: Expr, b: Expr) -> Expr:
    if isinstance(a, Num) and isinstance(b, Num):
        return Num(float(a.value) ** b.value)
    if b == ZERO:
        return ONE
    if b == ONE:
        return a
    return Bin("**", a, b)


def call(fn: str, *args: Expr, table: Table | None = None) -> Expr:
    nums = [a for a in args if isinstance(a, Num)]
    if table is None and len(nums) == len(args):
        vals = [a.value for a in nums]
        if fn in FUNCTIONS_1:
            return Num(float(FUNCTIONS_1[fn](vals[0])))
        if fn in FUNCTIONS_2:
            return Num(float(FUNCTIONS_2[fn](vals[0], vals[1])))
    return Call(fn, tuple(args), table)


# ---------------------------------------------------------------------------------------------
# parser

_TOKEN = re.compile(
    r"\s*(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)|(?P<name>[A-Za-z_][A-Za-z0-9_.]*)"
    r"|(?P<op>\*\*|[-+*/(),]))"
)


def _tokenize(text: str) -> list[tuple[str, str]]:
    pos, out = 0, []
    text = text.rstrip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if not m or m.end() == pos:
            raise ExprError(f"unexpected character {text[pos:].strip()[:1]!r} at position {pos} in {text!r}")
        kind = m.lastgroup
        assert kind is not None
        out.append((kind, m.group(kind)))
        pos = m.end()
    out.append(("end", ""))
    return out


class _Parser:
    def __init__(self, text: str, tables: Mapping[str, Table]) -> None:
        self.text = text
        self.toks = _tokenize(text)
        self.i = 0
        self.tables = tables

    def peek(self) -> tuple[str, str]:
        return self.toks[self.i]

    def take(self, value: str | None = None) -> tuple[str, str]:
        tok = self.toks[self.i]
        if value is not None and tok[1] != value:
            raise ExprError(f"expected {value!r} but found {tok[1] or 'end'!r} in {self.text!r}")
        self.i += 1
        return tok

    def expr(self) -> Expr:
        left = self.term()
        while self.peek()[1] in ("+", "-"):
            op = self.take()[1]
            left = _bin(op, left, self.term())
        return left

    def term(self) -> Expr:
        left = self.unary()
        while self.peek()[1] in ("*", "/"):
            op = self.take()[1]
            left = _bin(op, left, self.unary())
        return left

    def unary(self) -> Expr:
        if self.peek()[1] == "-":
            self.take()
            return neg(self.unary())
        if self.peek()[1] == "+":
            self.take()
            return self.unary()
        return self.power()

    def power(self) -> Expr:
        base = self.atom()
        if self.peek()[1] == "**":
            self.take()
            return power(base, self.unary())  # right-associative, binds tighter than unary minus on the left
        return base

    def atom(self) -> Expr:
        kind, val = self.take()
        if kind == "num":
            return Num(float(val))
        if kind == "name":
            if self.peek()[1] == "(":
                return self.call(val)
            return Name(val)
        if val == "(":
            e = self.expr()
            self.take(")")
            return e
        raise ExprError(f"unexpected {val or 'end'!r} in {self.text!r}")

    def call(self, fn: str) -> Expr:
        self.take("(")
        args = [self.expr()]
        while self.peek()[1] == ",":
            self.take()
            args.append(self.expr())
        self.take(")")
        if fn in self.tables:
            table = self.tables[fn]
            want = getattr(table, "arity", len(args))
            if len(args) != want:
                raise ExprError(f"table {fn}() takes {want} argument(s), got {len(args)} in {self.text!r}")
            return Call(fn, tuple(args), table)
        want = 1 if fn in FUNCTIONS_1 else 2 if fn in FUNCTIONS_2 else None
        if want is None:
            allowed = ", ".join(sorted([*FUNCTIONS_1, *FUNCTIONS_2, *self.tables]))
            raise ExprError(f"unknown function {fn}() in {self.text!r} (allowed: {allowed})")
        if len(args) != want:
            raise ExprError(f"{fn}() takes {want} argument(s), got {len(args)} in {self.text!r}")
        return call(fn, *args)


def parse(text: str | float | int, tables: Mapping[str, Table] | None = None) -> Expr:
    """Parse a law into an expression tree.

    Parameters
    ----------
    text : str or number
        The law. Numbers are accepted as they are (YAML gives them as floats).
    tables : mapping, optional
        Model-declared lookup tables, callable as functions by name.

    Raises
    ------
    ExprError
        With the offending text when the law does not parse.
    """
    if isinstance(text, bool):
        raise ExprError(f"expected a number or an expression, got {text!r}")
    if isinstance(text, (int, float)):
        return Num(float(text))
    if not isinstance(text, str) or not text.strip():
        raise ExprError(f"expected a number or an expression, got {text!r}")
    p = _Parser(text, tables or {})
    e = p.expr()
    if p.peek()[0] != "end":
        raise ExprError(f"unexpected {p.peek()[1]!r} after a complete expression in {text!r}")
    return e


# ---------------------------------------------------------------------------------------------
# code generation

def compile_many(exprs: Sequence[Expr]) -> Callable[[Env], list[Value]]:
    """One function evaluating every expression of ``exprs`` from one environment.

    The values are those each expression's :meth:`Expr.compile` gives (the same operations in the
    same order), as a list in the order of ``exprs``; one call instead of one per law and per node.
    """
    return _generated(list(exprs), single=False)


def _generated(exprs: list[Expr], single: bool) -> Callable[[Env], Any]:
    gen = _CodeGen()
    results = [gen.emit(e) for e in exprs]
    ret = results[0] if single else "[" + ", ".join(results) + "]"
    body = "".join(f"    {line}\n" for line in gen.lines)
    source = f"def _law(env):\n{body}    return {ret}\n"
    label = f"{len(exprs)} law(s), {len(gen.lines)} nodes"
    namespace = dict(gen.globals)
    exec(compile(source, f"<law {label}>", "exec"), namespace)  # source built from the parsed tree only
    f: Callable[[Env], Any] = namespace["_law"]
    return f


class _CodeGen:
    """Straight-line code of expression trees: each node a local, a node object met twice once."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.globals: dict[str, Any] = {"_pow": np.power, "_where": np.where, "_asarray": np.asarray}
        self._memo: dict[int, str] = {}
        self._keep: list[Expr] = []  # the nodes memoised by id stay alive while the code is built

    def _local(self, line: str) -> str:
        name = f"v{len(self.lines)}"
        self.lines.append(f"{name} = {line}")
        return name

    def _global(self, value: Any) -> str:
        name = f"_g{len(self.globals)}"
        self.globals[name] = value
        return name

    def emit(self, e: Expr) -> str:
        """The name (or literal) holding the value of ``e``, emitting the lines it needs (one
        Python frame per level of the tree, as evaluating it node by node would take)."""
        hit = self._memo.get(id(e))
        if hit is not None:
            return hit
        if isinstance(e, Num):
            out = repr(e.value) if math.isfinite(e.value) else self._global(e.value)
        elif isinstance(e, Name):
            out = self._local(f"env[{e.name!r}]")
        elif isinstance(e, Bin):
            a, b = self.emit(e.a), self.emit(e.b)
            out = self._local(f"_pow({a}, {b})" if e.op == "**" else f"{a} {e.op} {b}")
        elif isinstance(e, Call):
            args = [self.emit(a) for a in e.args]
            if e.table is not None:
                out = self._local(f"{self._global(e.table)}({', '.join(args)})")
            elif e.fn in FUNCTIONS_1 or e.fn in FUNCTIONS_2:
                fn = FUNCTIONS_1.get(e.fn) or FUNCTIONS_2[e.fn]
                out = self._local(f"{self._global(fn)}({', '.join(args)})")
            else:
                cmp = ">=" if e.fn == "step_ge" else "<="
                out = self._local(f"_where(_asarray({args[0]}) {cmp} {args[1]}, 1.0, 0.0)")
        else:
            raise ExprError(f"cannot compile {e!r}")
        self._memo[id(e)] = out
        self._keep.append(e)
        return out


def is_affine(e: Expr, names: set[str] | frozenset[str]) -> bool:
    """Whether ``e`` is affine in ``names`` by its structure (sums, products with factors free of
    ``names``, division by such factors); functions of ``names`` (``abs``, ``sign``, ``min``, …)
    are not, even where their derivative happens to be constant.

    >>> is_affine(parse("2 * (1 + 0.004 * (T - 20)) * i ** 2"), {"T"})
    True
    >>> is_affine(parse("20 + 20 * sign(T - 30)"), {"T"})
    False
    """
    if not (e.free() & names):
        return True
    if isinstance(e, Name):
        return True
    if isinstance(e, Bin):
        a_free, b_free = not (e.a.free() & names), not (e.b.free() & names)
        if e.op in "+-":
            return is_affine(e.a, names) and is_affine(e.b, names)
        if e.op == "*":
            return (a_free and is_affine(e.b, names)) or (b_free and is_affine(e.a, names))
        if e.op == "/":
            return b_free and is_affine(e.a, names)
        return e.b == ONE and is_affine(e.a, names)
    return False


def evaluate_const(e: Expr) -> float:
    """Value of an expression with no free names (e.g. geometry after inlining constants)."""
    if e.free():
        raise ExprError(f"{e} still depends on {', '.join(sorted(e.free()))}")
    return float(np.asarray(e.compile()({})))


__all__ = ["Expr", "ExprError", "Num", "Name", "Bin", "Call", "parse", "as_expr", "compile_many", "evaluate_const",
           "is_affine"]
