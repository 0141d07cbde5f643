"""Test the restricted evaluator of user-defined policy cost functions."""

from __future__ import annotations

import math
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridgeos_agent.expressions import (
    MAX_DEPTH,
    MAX_LENGTH,
    ExpressionError,
    compile_expression,
)

NAMES = ("cpu", "ram", "io", "latency", "weight")
VALUES = {"cpu": 0.5, "ram": 256.0, "io": 3.0, "latency": 0.02, "weight": 2.0}


def value_of(text: str, **variables: float) -> float:
    """Compile and evaluate an expression over the test variables."""
    return compile_expression(text, NAMES).evaluate({**VALUES, **variables})


def error_of(text: str, names: tuple[str, ...] = NAMES) -> str:
    """Return the message an expression that must be refused is refused with."""
    with pytest.raises(ExpressionError) as info:
        compile_expression(text, names).evaluate(VALUES)
    return str(info.value)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("1 + 2 * 3", 7.0),
        ("(1 + 2) * 3", 9.0),
        ("2 ** 3 ** 2", 512.0),
        ("-2 ** 2", -4.0),
        ("7 // 2", 3.0),
        ("-7 // 2", -4.0),
        ("7 % 3", 1.0),
        ("-7 % 3", 2.0),
        ("1 / 4", 0.25),
        ("+cpu", 0.5),
        ("cpu * weight + ram / 256", 2.0),
        ("10 - 4 - 3", 3.0),
        ("1e3 * 2", 2000.0),
    ],
)
def test_arithmetic_follows_python_precedence(text: str, expected: float) -> None:
    assert value_of(text) == expected


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("1 < 2", 1.0),
        ("2 <= 1", 0.0),
        ("1 < 2 < 3", 1.0),
        ("1 < 3 < 2", 0.0),
        ("cpu == 0.5 != ram", 1.0),
        ("not cpu", 0.0),
        ("not 0", 1.0),
        ("0 or 5", 5.0),
        ("3 and 0", 0.0),
        ("3 and 4", 4.0),
        ("0 and 1 / 0", 0.0),
        ("1 or 1 / 0", 1.0),
        ("ram if cpu > 1 else io", 3.0),
        ("1 / 0 if 0 else 9", 9.0),
    ],
)
def test_comparisons_and_conditionals_follow_python(text: str, expected: float) -> None:
    assert value_of(text) == expected


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("min(3, 1, 2)", 1.0),
        ("max(cpu, io)", 3.0),
        ("abs(-4)", 4.0),
        ("sqrt(16)", 4.0),
        ("log(exp(2))", 2.0),
        ("log(8, 2)", 3.0),
        ("pow(2, 10)", 1024.0),
        ("clamp(5, 0, 1)", 1.0),
        ("clamp(-5, 0, 1)", 0.0),
        ("clamp(cpu, 0, 1)", 0.5),
    ],
)
def test_whitelisted_functions_compute(text: str, expected: float) -> None:
    assert value_of(text) == pytest.approx(expected)


def test_result_is_a_float() -> None:
    assert type(value_of("1 + 1")) is float
    assert type(value_of("1 < 2")) is float


def test_compiled_expression_is_reused_with_new_variables() -> None:
    expression = compile_expression("cpu * 2", ["cpu"])
    assert [expression.evaluate({"cpu": x}) for x in (1.0, 2.5)] == [2.0, 5.0]
    assert expression.names == frozenset({"cpu"})
    assert expression.source == "cpu * 2"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("__import__('os')", "cannot call '__import__'"),
        ("__import__", "name '__import__' is not allowed"),
        ("().__class__", "attribute access is not allowed"),
        ("cpu.__class__", "attribute access is not allowed"),
        ("(1).real", "attribute access is not allowed"),
        ("__builtins__", "name '__builtins__' is not allowed"),
        ("cpu[0]", "subscripts are not allowed"),
        ("(lambda: 1)()", "cannot call"),
        ("lambda: 1", "lambdas are not allowed"),
        ("[x for x in (1, 2)]", "comprehensions are not allowed"),
        ("sum(x for x in (1, 2))", "cannot call 'sum'"),
        ("min(x for x in (1, 2))", "comprehensions are not allowed"),
        ("{x: 1 for x in (1,)}", "comprehensions are not allowed"),
        ("'a'", "strings are not allowed"),
        ("b'a'", "strings are not allowed"),
        ("f'{cpu}'", "f-strings are not allowed"),
        ("(cpu := 1)", "assignments (:=) are not allowed"),
        ("open('/etc/passwd')", "cannot call 'open'"),
        ("eval('1')", "cannot call 'eval'"),
        ("cpu(1)", "cannot call 'cpu'"),
        ("min", "function 'min' must be called"),
        ("log(8, base=2)", "keyword arguments are not allowed in log()"),
        ("max(*[1, 2])", "starred arguments are not allowed"),
        ("min(1)", "min() takes 2 or more arguments, not 1"),
        ("sqrt(1, 2)", "sqrt() takes 1 arguments, not 2"),
        ("clamp(1, 2)", "clamp() takes 3 arguments, not 2"),
        ("unknown + 1", "unknown name 'unknown'"),
        ("True", "constant True is not a number"),
        ("None", "constant None is not a number"),
        ("1j", "constant 1j is not a number"),
        ("...", "constant Ellipsis is not a number"),
        ("1 & 2", "operator '&' is not allowed"),
        ("~1", "operator '~' is not allowed"),
        ("1 << 2", "operator '<<' is not allowed"),
        ("cpu is 1", "operator 'is' is not allowed"),
        ("1 in 2", "operator 'in' is not allowed"),
        ("[1]", "lists are not allowed"),
        ("{1: 2}", "dicts are not allowed"),
        ("1 +", "invalid syntax"),
        ("import os", "invalid syntax"),
        ("cpu; 1", "invalid syntax"),
        ("", "expression is empty"),
        ("   ", "expression is empty"),
    ],
)
def test_unsafe_or_unknown_constructs_are_refused_with_a_reason(text: str, message: str) -> None:
    assert message in error_of(text)


def test_errors_name_the_column() -> None:
    with pytest.raises(ExpressionError) as info:
        compile_expression("cpu + ram.real", NAMES)
    assert info.value.column == 10
    assert str(info.value) == "attribute access is not allowed at column 10"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("  cpu.real", "attribute access is not allowed at column 6"),
        ("\n  cpu + x", "unknown name 'x' at line 2, column 9"),
        ("   1 1", "invalid syntax at column 6"),
    ],
)
def test_positions_count_leading_whitespace(text: str, message: str) -> None:
    assert error_of(text) == message


def test_leading_and_trailing_whitespace_is_accepted() -> None:
    assert value_of("  cpu * 2\n") == 1.0


def test_errors_name_the_line_of_multiline_expressions() -> None:
    with pytest.raises(ExpressionError) as info:
        compile_expression("(cpu +\n x)", NAMES)
    assert str(info.value) == "unknown name 'x' at line 2, column 2"


@pytest.mark.parametrize("text", ["9 ** 9 ** 9", "2 ** 101", "pow(2, -101)", "2 ** (10 ** 3)"])
def test_huge_exponents_are_refused(text: str) -> None:
    assert "is beyond ±100" in error_of(text)


@pytest.mark.parametrize(
    "text", ["1e300 ** 2", "1e308 * 10", "1e308 + 1e308", "-1e308 - 1e308", "exp(1000)", "1e300 / 1e-300"]
)
def test_overflowing_results_are_refused(text: str) -> None:
    assert "overflows" in error_of(text)


def test_huge_integer_literal_is_refused() -> None:
    assert "too large" in error_of("1" + "0" * 400)


@pytest.mark.parametrize("text", ["1 / 0", "cpu // (ram - 256)", "5 % 0", "1 / (cpu - 0.5)"])
def test_division_by_zero_is_reported(text: str) -> None:
    assert "division by zero at column" in error_of(text)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("sqrt(-1)", "sqrt of negative number -1"),
        ("log(0)", "log of 0 in base 2.71828 is undefined"),
        ("log(8, 1)", "log of 8 in base 1 is undefined"),
        ("(-8) ** (1 / 3)", "power -8 ** 0.333333 is undefined"),
        ("0 ** -1", "power 0 ** -1 is undefined"),
        ("clamp(1, 2, 0)", "clamp bounds are reversed"),
    ],
)
def test_undefined_math_is_reported(text: str, message: str) -> None:
    assert message in error_of(text)


def test_long_input_is_refused_before_parsing() -> None:
    text = "+".join(["1"] * (MAX_LENGTH // 2 + 1))
    assert f"longer than {MAX_LENGTH}" in error_of(text)


@pytest.mark.parametrize(
    "text",
    [
        "-" * 200 + "1",
        "(" * 60 + "1" + ")" * 60 + "+" + "abs(" * 60 + "1" + ")" * 60,
        "+".join(["1"] * 60),
        "(" * 300 + "1" + ")" * 300,
    ],
)
def test_deep_nesting_is_refused(text: str) -> None:
    message = error_of(text)
    assert f"nested deeper than {MAX_DEPTH}" in message or "too many nested parentheses" in message


def test_nesting_within_the_limit_is_accepted() -> None:
    assert value_of("+".join(["1"] * 40)) == 40.0


def test_missing_variable_is_reported_at_evaluation() -> None:
    expression = compile_expression("cpu + ram", NAMES)
    with pytest.raises(ExpressionError, match="variable 'ram' has no value"):
        expression.evaluate({"cpu": 1.0})


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_variable_is_refused(bad: float) -> None:
    with pytest.raises(ExpressionError, match="variable 'cpu' is not a finite number"):
        compile_expression("cpu > 0", NAMES).evaluate({"cpu": bad})


def test_names_outside_the_allowed_set_are_refused_even_if_passed_at_evaluation() -> None:
    with pytest.raises(ExpressionError, match="unknown name 'secret'"):
        compile_expression("secret", ["cpu"])


def test_dunder_names_are_refused_even_when_allowed() -> None:
    with pytest.raises(ExpressionError, match="name '__class__' is not allowed"):
        compile_expression("__class__", ["__class__"])


def test_non_string_expression_is_refused() -> None:
    with pytest.raises(ExpressionError, match="must be a string"):
        compile_expression(42, NAMES)  # type: ignore[arg-type]


def test_evaluation_takes_microseconds() -> None:
    expression = compile_expression("max(cpu * weight, 1) + ram / 1024 - io ** 2 if latency < 0.1 else 0", NAMES)
    runs = 20_000
    start = time.perf_counter()
    for _ in range(runs):
        expression.evaluate(VALUES)
    # Generous so a loaded CI machine passes; typical is 1-3 µs per evaluation.
    assert (time.perf_counter() - start) / runs < 50e-6


# Random expressions over small positive numbers and safe operators only, so Python's
# own arithmetic is a valid oracle.
_leaves = st.one_of(
    st.integers(min_value=0, max_value=50).map(str),
    st.floats(min_value=0.5, max_value=50, allow_nan=False).map(lambda f: f"{f!r}"),
    st.sampled_from(NAMES),
)


def _combine(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    binary = st.tuples(children, st.sampled_from(["+", "-", "*", "<", ">=", "==", "and", "or"]), children).map(
        lambda t: f"({t[0]} {t[1]} {t[2]})"
    )
    unary = st.tuples(st.sampled_from(["-", "not "]), children).map(lambda t: f"({t[0]}{t[1]})")
    call = st.tuples(st.sampled_from(["min", "max"]), children, children).map(lambda t: f"{t[0]}({t[1]}, {t[2]})")
    conditional = st.tuples(children, children, children).map(lambda t: f"({t[0]} if {t[1]} else {t[2]})")
    return st.one_of(binary, unary, call, conditional, children.map(lambda c: f"abs({c})"))


@settings(max_examples=300, deadline=None)
@given(st.recursive(_leaves, _combine, max_leaves=12))
def test_evaluator_agrees_with_python_on_safe_expressions(text: str) -> None:
    # eval is the oracle here only: the text comes from the generator above, never from a user.
    expected = float(eval(text, {"__builtins__": {}, "min": min, "max": max, "abs": abs}, dict(VALUES)))
    assert value_of(text) == pytest.approx(expected)


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=60))
def test_arbitrary_text_either_compiles_or_raises_expression_error(text: str) -> None:
    try:
        compile_expression(text, NAMES).evaluate(VALUES)
    except ExpressionError:
        pass
