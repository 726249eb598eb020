"""Law expressions: grammar, rejection, symbolic derivatives and compiled closures.

Oracle: Python itself. Every law string generated here is also valid Python with the same
precedence (``-2**2``, right-associative ``**``), so ``eval`` of the same text with ``math``
functions gives the independent value, and central finite differences of that ``eval`` give the
independent derivative.
"""
from __future__ import annotations

import math
import zlib

import numpy as np
import pytest

from thermal_edge.lptn.expr import Bin, Call, ExprError, Name, Num, compile_many, evaluate_const, parse

PY_FUNCS = {
    "exp": math.exp,
    "log": math.log,
    "sqrt": math.sqrt,
    "tanh": math.tanh,
    "abs": abs,
    "sign": lambda x: float(np.sign(x)),
    "min": min,
    "max": max,
}


def py_eval(text: str, env: dict) -> float:
    return float(eval(text, {"__builtins__": {}}, {**PY_FUNCS, **env}))  # the test oracle, without builtins


def value(text: str, **env) -> float:
    return float(np.asarray(parse(text).compile()(env)))


# ---------------------------------------------------------------------------------------------
# grammar and precedence


@pytest.mark.parametrize(
    "text, expected",
    [
        ("-2**2", -4.0),
        ("2**3**2", 512.0),
        ("(2**3)**2", 64.0),
        ("2**-1", 0.5),
        ("-2**-2", -0.25),
        ("10-3-2", 5.0),
        ("64/4/2", 8.0),
        ("2+3*4", 14.0),
        ("2*3**2", 18.0),
        ("(2+3)*4", 20.0),
        ("--3", 3.0),
        ("+-+3", -3.0),
        ("1.5e3 + .5 + 2.", 1502.5),
        ("2e-3*1E+3", 2.0),
    ],
)
def test_precedence_of_numbers(text, expected):
    assert value(text) == pytest.approx(expected, rel=1e-15)
    assert py_eval(text, {}) == pytest.approx(expected, rel=1e-15)  # the oracle agrees


@pytest.mark.parametrize(
    "text",
    ["a-b-c", "a/b/c", "a-b+c", "a*b/c*a", "-a**2", "a**b**c", "-a**-b", "a - -b", "a*-b", "(a-b)*(c-a)/b"],
)
def test_precedence_with_names(text):
    env = {"a": 1.7, "b": 0.6, "c": 1.3}
    assert value(text, **env) == pytest.approx(py_eval(text, env), rel=1e-14)


def test_a_minus_b_minus_c_is_left_associative():
    assert value("a-b-c", a=10.0, b=3.0, c=2.0) == 5.0  # (10-3)-2, not 10-(3-2) = 9


@pytest.mark.parametrize(
    "text, x",
    [
        ("exp(x)", 0.7),
        ("log(x)", 2.5),
        ("sqrt(x)", 6.25),
        ("tanh(x)", -0.4),
        ("abs(x)", -3.5),
        ("abs(x)", 2.0),
        ("sign(x)", -2.0),
        ("sign(x)", 3.0),
        ("sign(x)", 0.0),
        ("min(x, 1.5)", 0.2),
        ("min(x, 1.5)", 2.2),
        ("max(x, 1.5)", 0.2),
        ("max(x, 1.5)", 2.2),
        ("max(min(x, 2), -1)", 7.0),
    ],
)
def test_every_whitelisted_function(text, x):
    assert value(text, x=x) == pytest.approx(py_eval(text, {"x": x}), rel=1e-15, abs=0)


def test_names_with_dots_and_free_names():
    e = parse("P20 * (1 + alpha_cu * (T.sw_1 - 20))")
    assert e.free() == {"P20", "alpha_cu", "T.sw_1"}
    assert float(e.compile()({"P20": 100.0, "alpha_cu": 0.004, "T.sw_1": 70.0})) == pytest.approx(120.0)


def test_numbers_pass_through_and_evaluate_const():
    assert evaluate_const(parse(2.5)) == 2.5
    assert evaluate_const(parse(3)) == 3.0
    assert evaluate_const(parse("exp(0) + sqrt(16)")) == 5.0
    with pytest.raises(ExprError):
        evaluate_const(parse("x + 1"))


# ---------------------------------------------------------------------------------------------
# rejection


@pytest.mark.parametrize(
    "text",
    [
        "__import__('os')",
        '__import__("os").system("true")',
        "(x).real",
        "x.__class__()",  # a dotted name followed by a call is an unknown function, never an attribute
        "(1).__class__",
        "'abc'.upper()",
        "x[0]",
        "lambda: 1",
        "lambda x: x",
        "1 +",
        "1 + * 2",
        "2 **",
        "(1 + 2",
        "1 + 2)",
        "()",
        "",
        "   ",
        "x y",
        "1 if x else 2",
        "x == 1",
        "x = 1",
        "x; y",
        "x % 2",
        "x // 2",
        "x @ y",
        "2 ^ 3",
        "open('f')",
        "eval('1')",
        "exec('1')",
        "getattr(x, 'y')",
        "pow(2, 3)",
        "foo(1)",
        "sin(x)",
        "exp()",
        "exp(1, 2)",
        "log(x, 10)",
        "min(1)",
        "max(1, 2, 3)",
        "sign()",
        "abs(1, 2)",
        "exp(,)",
        "exp(1,)",
    ],
)
def test_rejected_with_expr_error(text):
    with pytest.raises(ExprError):
        parse(text)


@pytest.mark.parametrize("bad", [True, False, None, [], {}, b"1"])
def test_non_law_values_rejected(bad):
    with pytest.raises(ExprError):
        parse(bad)


def test_messages_say_what_is_wrong():
    with pytest.raises(ExprError, match="unknown function"):
        parse("foo(1)")
    with pytest.raises(ExprError, match=r"takes 1 argument"):
        parse("exp(1, 2)")
    with pytest.raises(ExprError, match=r"takes 2 argument"):
        parse("min(1)")


def test_dotted_name_is_only_a_name():
    """``x.__class__`` is a single opaque name (dots serve ``T.<node>``): it evaluates only by
    looking the whole text up in the environment, never by attribute access."""
    e = parse("x.__class__")
    assert e.free() == {"x.__class__"}
    with pytest.raises(KeyError):
        e.compile()({"x": 1.0})


def test_division_by_constant_zero_rejected():
    with pytest.raises(ExprError):
        parse("x / 0")


# ---------------------------------------------------------------------------------------------
# symbolic derivatives vs central finite differences of the Python oracle

VARS = ("x", "y", "z")


class Gen:
    """Random law strings, valid Python too, with the sub-expressions where the law has a kink
    (arguments of abs/sign, differences of min/max), so that test points avoid them."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.kinks: list[str] = []
        self.used: set[str] = set()

    def leaf(self) -> str:
        if self.rng.random() < 0.7:
            v = str(self.rng.choice(VARS))
            self.used.add(v)
            return v
        return repr(round(float(self.rng.uniform(0.2, 2.5)), 3))

    def expr(self, depth: int) -> str:
        if depth == 0:
            return self.leaf()
        r = self.rng
        kind = str(
            r.choice(
                ["+", "-", "*", "/", "neg", "exp", "log", "sqrt", "tanh", "abs", "sign", "min", "max",
                 "powc", "powi", "powv", "cpow"]
            )
        )
        a = self.expr(depth - 1)
        if kind in ("+", "-", "*"):
            return f"({a} {kind} {self.expr(depth - 1)})"
        if kind == "/":
            return f"({a} / (1.6 + tanh({self.expr(depth - 1)})))"
        if kind == "neg":
            return f"(-{a})"
        if kind == "exp":
            return f"exp(tanh({a}))"
        if kind == "log":
            return f"log(0.3 + {a} * {a})"
        if kind == "sqrt":
            return f"sqrt(0.2 + {a} * {a})"
        if kind == "tanh":
            return f"tanh({a})"
        if kind == "abs":
            self.kinks.append(a)
            return f"abs({a})"
        if kind == "sign":
            self.kinks.append(a)
            return f"(sign({a}) * {self.expr(depth - 1)})"
        if kind in ("min", "max"):
            b = self.expr(depth - 1)
            self.kinks.append(f"(({a}) - ({b}))")
            return f"{kind}({a}, {b})"
        if kind == "powc":  # constant non-integer exponent, positive base
            c = float(r.choice([0.5, 1.5, 2.5, -0.5, -1.5, 2.5667]))
            return f"(0.4 + {a} * {a}) ** {c!r}"
        if kind == "powi":  # integer exponent, any base
            return f"({a}) ** {int(r.choice([2, 3]))}"
        if kind == "powv":  # variable exponent, positive base
            return f"(1.2 + tanh({a})) ** tanh({self.expr(depth - 1)})"
        # constant base, variable exponent
        return f"{float(r.choice([0.5, 2.0, 3.0]))!r} ** tanh({a})"


def _cases(n: int, seed: int):
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        g = Gen(rng)
        text = g.expr(int(rng.integers(2, 5)))
        if not g.used or not _has_point(rng, g.kinks):
            continue  # e.g. min(x, x): no point away from the kink
        out.append((text, tuple(g.kinks)))
    return out


def _has_point(rng, kinks) -> bool:
    for _ in range(200):
        env = {v: float(rng.uniform(-1.5, 1.5)) for v in VARS}
        if all(abs(py_eval(k, env)) > 1e-2 for k in kinks):
            return True
    return False


CASES = _cases(150, 20240611)


def test_random_cases_cover_every_function_and_power_form():
    texts = " ".join(t for t, _ in CASES)
    for fn in ("exp(", "log(", "sqrt(", "tanh(", "abs(", "sign(", "min(", "max(", " / ", " - ", "(-"):
        assert fn in texts, fn
    assert any(") ** tanh(" in t for t, _ in CASES)  # variable exponent
    assert any(t.count("** 2.5667") for t, _ in CASES)  # constant non-integer exponent
    assert any(") ** 3" in t or ") ** 2" in t for t, _ in CASES)  # integer exponent


def _point(rng, kinks):
    for _ in range(200):
        env = {v: float(rng.uniform(-1.5, 1.5)) for v in VARS}
        if all(abs(py_eval(k, env)) > 1e-2 for k in kinks):
            return env
    pytest.skip("no point away from the kinks")  # pragma: no cover


@pytest.mark.parametrize("text, kinks", CASES, ids=[f"r{i}" for i in range(len(CASES))])
def test_random_derivatives_match_finite_differences(text, kinks):
    e = parse(text)
    rng = np.random.default_rng(zlib.crc32(text.encode()))
    f = e.compile()
    for _ in range(3):
        env = _point(rng, kinks)
        ref = py_eval(text, env)
        assert float(np.asarray(f(env))) == pytest.approx(ref, rel=1e-12, abs=1e-12)
        for v in VARS:
            h = 1e-6
            fd = (py_eval(text, {**env, v: env[v] + h}) - py_eval(text, {**env, v: env[v] - h})) / (2 * h)
            d = float(np.asarray(e.diff(v).compile()(env)))
            assert d == pytest.approx(fd, rel=1e-6, abs=1e-7 * max(1.0, abs(ref))), (text, v, env)


@pytest.mark.parametrize("text, kinks", CASES[:40], ids=[f"r{i}" for i in range(40)])
def test_compiled_closures_on_arrays(text, kinks):
    """Laws and their derivatives evaluate elementwise on numpy arrays (whole time series)."""
    rng = np.random.default_rng(7)
    pts = [_point(rng, kinks) for _ in range(25)]
    arr = {v: np.array([p[v] for p in pts]) for v in VARS}
    e = parse(text)
    got = np.broadcast_to(np.asarray(e.compile()(arr), float), (25,))
    ref = np.array([py_eval(text, p) for p in pts])
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    for v in VARS:
        d = np.broadcast_to(np.asarray(e.diff(v).compile()(arr), float), (25,))
        d1 = np.array([float(np.asarray(e.diff(v).compile()(p))) for p in pts])
        np.testing.assert_allclose(d, d1, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize(
    "text, x, expected",
    [
        ("x ** 3", -2.0, 12.0),  # constant exponent: defined for negative bases
        ("x ** 2", 0.0, 0.0),
        ("x ** 0.5", 4.0, 0.25),
        ("2 ** x", 3.0, 8 * math.log(2)),
        ("x ** x", 2.0, 4 * (math.log(2) + 1)),
        ("abs(x)", -3.0, -1.0),
        ("sign(x) * x", -3.0, -1.0),
        ("min(x, 2)", 1.0, 1.0),
        ("min(x, 2)", 3.0, 0.0),
        ("max(x, 2)", 1.0, 0.0),
        ("max(x, 2)", 3.0, 1.0),
        ("max(2 * x, x ** 2)", 3.0, 6.0),
        ("max(2 * x, x ** 2)", 1.0, 2.0),
        ("log(x)", 4.0, 0.25),
        ("sqrt(x)", 9.0, 1 / 6),
        ("tanh(x)", 0.5, 1 - math.tanh(0.5) ** 2),
        ("exp(2 * x)", 0.5, 2 * math.e),
        ("1 / x", 2.0, -0.25),
    ],
)
def test_known_derivatives(text, x, expected):
    d = parse(text).diff("x")
    assert float(np.asarray(d.compile()({"x": x}))) == pytest.approx(expected, rel=1e-14, abs=1e-15)


def test_derivative_of_unrelated_name_is_zero():
    e = parse("exp(x) * y + min(x, y)")
    assert float(np.asarray(e.diff("z").compile()({"x": 1.0, "y": 2.0}))) == 0.0


@pytest.mark.parametrize("text, kinks", CASES[:40], ids=[f"r{i}" for i in range(40)])
def test_printed_form_reparses_to_the_same_law(text, kinks):
    """``str`` of a tree (used in messages and for derivatives) is itself a valid law."""
    rng = np.random.default_rng(11)
    e = parse(text)
    e2 = parse(str(e))
    for _ in range(3):
        env = _point(rng, kinks)
        assert float(np.asarray(e2.compile()(env))) == pytest.approx(float(np.asarray(e.compile()(env))), rel=1e-13, abs=1e-13)


def test_one_function_for_many_laws_gives_each_laws_value():
    """``compile_many`` returns, in order, what each law's own evaluation gives (Python's eval)."""
    texts = [t for t, _ in CASES[:60]]
    many = compile_many([parse(t) for t in texts])
    rng = np.random.default_rng(11)
    for _ in range(5):
        env = {v: float(rng.uniform(0.1, 1.4)) for v in VARS}
        ok = [i for i, t in enumerate(texts) if _finite(t, env)]
        got = many(env)
        assert len(got) == len(texts)
        for i in ok:
            assert float(np.asarray(got[i])) == pytest.approx(py_eval(texts[i], env), rel=1e-12, abs=1e-12)


def _finite(text, env) -> bool:
    try:
        return math.isfinite(py_eval(text, env))
    except (ValueError, ZeroDivisionError, OverflowError):
        return False


def test_deeply_nested_law_compiles_beyond_pythons_parenthesis_limit():
    """Generated code is one statement per node: a tree 600 levels deep (Python's parser refuses
    200 nested parentheses) evaluates, to the value counted another way."""
    e = Name("x")
    for k in range(600):
        e = Bin("*" if k % 2 else "+", e, Num(1.0 if k % 2 else 0.5))
    assert float(e.compile()({"x": 2.0})) == 2.0 + 0.5 * 300


def test_a_subtree_met_twice_is_evaluated_once():
    calls = []

    def table(x):
        calls.append(x)
        return np.asarray(x) * 3.0

    shared = Call("tab", (Name("x"),), table)
    f = compile_many([Bin("+", shared, shared), Bin("*", shared, Num(2.0))])
    assert [float(v) for v in f({"x": 2.0})] == [12.0, 12.0]
    assert len(calls) == 1


def test_non_finite_constants_and_numpy_scalar_division():
    """Constants without a literal (inf, nan) evaluate, and a division by a numpy scalar zero gives
    inf as it does on arrays (the service's one-tick environment holds numpy scalars)."""
    f = Bin("+", Name("x"), Num(math.inf)).compile()
    assert f({"x": 1.0}) == math.inf
    g = Bin("*", Name("x"), Num(math.nan)).compile()
    assert math.isnan(g({"x": 1.0}))
    with np.errstate(divide="ignore"):
        assert parse("a / b").compile()({"a": 1.0, "b": np.float64(0.0)}) == math.inf
