"""Evaluate user-defined policy cost functions (thesis section 4.2) without eval.

The thesis loads cost functions as JavaScript code; here a cost function is an
arithmetic expression over named numbers. It is parsed once with ``ast`` and turned
into nested closures, so nothing in the text can reach Python objects: only numbers,
the variables it was compiled for, arithmetic, comparisons, conditionals and a few
whitelisted functions are understood, and everything else is refused with its column.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

__all__ = [
    "FUNCTIONS",
    "MAX_DEPTH",
    "MAX_EXPONENT",
    "MAX_LENGTH",
    "CompiledExpression",
    "ExpressionError",
    "compile_expression",
]

# Bounds that keep one cost function from stalling a Skill Manager's decision loop.
MAX_LENGTH = 1000
MAX_DEPTH = 50
MAX_EXPONENT = 100.0

Variables = Mapping[str, float]
Node = Callable[[Variables], float]


class ExpressionError(ValueError):
    """Report an expression that cannot be compiled or evaluated, with its position."""

    def __init__(self, message: str, column: int | None = None, line: int = 1) -> None:
        where = ""
        if column is not None:
            where = f" at column {column}" if line == 1 else f" at line {line}, column {column}"
        super().__init__(message + where)
        self.reason = message
        self.column = column
        self.line = line


def _finite(value: float, what: str, where: dict[str, int]) -> float:
    """Refuse an infinite or NaN result, which no cost comparison could use."""
    if not math.isfinite(value):
        raise ExpressionError(f"{what} overflows", **where)
    return value


def _power(base: float, exponent: float, where: dict[str, int]) -> float:
    """Raise to a bounded power, refusing results that are complex, infinite or undefined."""
    if abs(exponent) > MAX_EXPONENT:
        raise ExpressionError(f"exponent {exponent:g} is beyond ±{MAX_EXPONENT:g}", **where)
    try:
        # math.pow, unlike **, raises instead of returning a complex for (-8) ** (1/3).
        return _finite(math.pow(base, exponent), "power", where)
    except OverflowError:
        raise ExpressionError("power overflows", **where) from None
    except ValueError:
        raise ExpressionError(f"power {base:g} ** {exponent:g} is undefined", **where) from None


def _sqrt(x: float, where: dict[str, int]) -> float:
    """Take a square root, refusing negative numbers."""
    if x < 0:
        raise ExpressionError(f"sqrt of negative number {x:g}", **where)
    return math.sqrt(x)


def _log(x: float, base: float = math.e, *, where: dict[str, int]) -> float:
    """Take a logarithm, refusing non-positive numbers and bases."""
    if x <= 0 or base <= 0 or base == 1:
        raise ExpressionError(f"log of {x:g} in base {base:g} is undefined", **where)
    return math.log(x) if base == math.e else math.log(x, base)


def _exp(x: float, where: dict[str, int]) -> float:
    """Raise e to a power, refusing overflow."""
    try:
        return math.exp(x)
    except OverflowError:
        raise ExpressionError("exp overflows", **where) from None


def _clamp(x: float, low: float, high: float, where: dict[str, int]) -> float:
    """Limit a number to [low, high]."""
    if low > high:
        raise ExpressionError(f"clamp bounds are reversed ({low:g} > {high:g})", **where)
    return min(max(x, low), high)


# Each function's arity (min, max args) and implementation taking the node's position.
FUNCTIONS: dict[str, tuple[int, int | None, Callable[..., float]]] = {
    "min": (2, None, lambda *args, where: min(args)),
    "max": (2, None, lambda *args, where: max(args)),
    "abs": (1, 1, lambda x, where: abs(x)),
    "sqrt": (1, 1, _sqrt),
    "log": (1, 2, _log),
    "exp": (1, 1, _exp),
    "pow": (2, 2, _power),
    "clamp": (3, 3, _clamp),
}

_NOT_ALLOWED: dict[type[ast.AST], str] = {
    ast.Attribute: "attribute access is not allowed",
    ast.Subscript: "subscripts are not allowed",
    ast.Lambda: "lambdas are not allowed",
    ast.ListComp: "comprehensions are not allowed",
    ast.SetComp: "comprehensions are not allowed",
    ast.DictComp: "comprehensions are not allowed",
    ast.GeneratorExp: "comprehensions are not allowed",
    ast.JoinedStr: "f-strings are not allowed",
    ast.FormattedValue: "f-strings are not allowed",
    ast.NamedExpr: "assignments (:=) are not allowed",
    ast.Starred: "starred arguments are not allowed",
    ast.Tuple: "tuples are not allowed",
    ast.List: "lists are not allowed",
    ast.Set: "sets are not allowed",
    ast.Dict: "dicts are not allowed",
    ast.Await: "await is not allowed",
    ast.Yield: "yield is not allowed",
    ast.YieldFrom: "yield is not allowed",
    ast.Slice: "slices are not allowed",
}

_OPERATOR_SYMBOLS: dict[type[ast.AST], str] = {
    ast.MatMult: "@",
    ast.BitAnd: "&",
    ast.BitOr: "|",
    ast.BitXor: "^",
    ast.LShift: "<<",
    ast.RShift: ">>",
    ast.Invert: "~",
    ast.Is: "is",
    ast.IsNot: "is not",
    ast.In: "in",
    ast.NotIn: "not in",
}

_COMPARISONS: dict[type[ast.cmpop], Callable[[float, float], bool]] = {
    ast.Eq: lambda a, b: a == b,
    ast.NotEq: lambda a, b: a != b,
    ast.Lt: lambda a, b: a < b,
    ast.LtE: lambda a, b: a <= b,
    ast.Gt: lambda a, b: a > b,
    ast.GtE: lambda a, b: a >= b,
}


@dataclass(frozen=True, slots=True)
class CompiledExpression:
    """Hold a validated expression, ready to be evaluated many times."""

    source: str
    names: frozenset[str]
    _root: Node

    def evaluate(self, variables: Variables) -> float:
        """Compute the expression's value from the given variables."""
        for name in self.names:
            value = variables.get(name)
            if value is None:
                raise ExpressionError(f"variable {name!r} has no value")
            # A NaN would make every comparison false and hide the mistake downstream.
            if not math.isfinite(value):
                raise ExpressionError(f"variable {name!r} is not a finite number ({value!r})")
        return float(_finite(self._root(variables), "result", {}))


def compile_expression(text: str, allowed_names: Iterable[str]) -> CompiledExpression:
    """Parse and validate an expression over the allowed variable names."""
    if not isinstance(text, str):
        raise ExpressionError(f"expression must be a string, not {type(text).__name__}")
    if len(text) > MAX_LENGTH:
        raise ExpressionError(f"expression is {len(text)} characters long, longer than {MAX_LENGTH}")
    stripped = text.strip()
    if not stripped:
        raise ExpressionError("expression is empty")
    # Leading whitespace is an "unexpected indent" to the parser, yet harmless in a config.
    skipped = text[: len(text) - len(text.lstrip())]
    try:
        tree = ast.parse(stripped, mode="eval")
    except SyntaxError as exc:
        reason = "invalid syntax" if exc.msg == "invalid syntax" else f"invalid syntax: {exc.msg}"
        # Python reports column 0 for errors at the end of the input, which points nowhere.
        line, column = exc.lineno or 1, exc.offset or None
        if column is not None and line == 1:
            column += len(skipped) - (skipped.rfind("\n") + 1)
        raise ExpressionError(reason, column, line + skipped.count("\n")) from None
    except (ValueError, RecursionError, MemoryError) as exc:
        raise ExpressionError(f"invalid expression: {exc}") from None
    compiler = _Compiler(frozenset(allowed_names), skipped)
    root = compiler.compile(tree.body, 1)
    return CompiledExpression(text, frozenset(compiler.used), root)


class _Compiler:
    """Turn a parsed expression into closures, refusing anything outside the grammar."""

    def __init__(self, allowed: frozenset[str], skipped: str = "") -> None:
        self.allowed = allowed
        self.used: set[str] = set()
        # The parser saw the text without its leading whitespace; report positions in the original.
        self.line_shift = skipped.count("\n")
        self.column_shift = len(skipped) - (skipped.rfind("\n") + 1)

    def at(self, node: ast.AST) -> dict[str, int]:
        """Return the 1-based position of a node in the original text, for an error."""
        if isinstance(node, ast.Attribute | ast.Subscript) and node.value.end_col_offset is not None:
            # Point at the '.' or '[' rather than the start of the object it applies to.
            line, column = node.value.end_lineno or 1, node.value.end_col_offset + 1
        else:
            line, column = getattr(node, "lineno", 1), getattr(node, "col_offset", 0) + 1
        if line == 1:
            column += self.column_shift
        return {"column": column, "line": line + self.line_shift}

    def compile(self, node: ast.AST, depth: int) -> Node:
        """Compile one node and its children, no deeper than MAX_DEPTH."""
        if depth > MAX_DEPTH:
            raise ExpressionError(f"expression is nested deeper than {MAX_DEPTH} levels", **self.at(node))
        if type(node) in _NOT_ALLOWED:
            raise ExpressionError(_NOT_ALLOWED[type(node)], **self.at(node))
        method = getattr(self, f"_{type(node).__name__.lower()}", None)
        if method is None:
            raise ExpressionError(f"{type(node).__name__} is not allowed", **self.at(node))
        return method(node, depth + 1)

    def _constant(self, node: ast.Constant, depth: int) -> Node:
        value = node.value
        if isinstance(value, str | bytes):
            raise ExpressionError("strings are not allowed", **self.at(node))
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ExpressionError(f"constant {value!r} is not a number", **self.at(node))
        try:
            number = _finite(float(value), "number", self.at(node))
        except OverflowError:
            raise ExpressionError("number is too large", **self.at(node)) from None
        return lambda variables: number

    def _name(self, node: ast.Name, depth: int) -> Node:
        name = node.id
        if name.startswith("__"):
            raise ExpressionError(f"name {name!r} is not allowed", **self.at(node))
        if name in FUNCTIONS:
            raise ExpressionError(f"function {name!r} must be called", **self.at(node))
        if name not in self.allowed:
            raise ExpressionError(f"unknown name {name!r}", **self.at(node))
        self.used.add(name)
        return lambda variables: variables[name]

    def _unaryop(self, node: ast.UnaryOp, depth: int) -> Node:
        operand = self.compile(node.operand, depth)
        if isinstance(node.op, ast.USub):
            return lambda variables: -operand(variables)
        if isinstance(node.op, ast.UAdd):
            return operand
        if isinstance(node.op, ast.Not):
            return lambda variables: float(not operand(variables))
        raise ExpressionError(f"operator {_OPERATOR_SYMBOLS[type(node.op)]!r} is not allowed", **self.at(node))

    def _binop(self, node: ast.BinOp, depth: int) -> Node:
        op = type(node.op)
        if op in _OPERATOR_SYMBOLS:
            raise ExpressionError(f"operator {_OPERATOR_SYMBOLS[op]!r} is not allowed", **self.at(node))
        left = self.compile(node.left, depth)
        right = self.compile(node.right, depth)
        where = self.at(node)
        isfinite = math.isfinite

        def overflow() -> ExpressionError:
            return ExpressionError("arithmetic overflows", **where)

        if op is ast.Add:

            def add(variables: Variables) -> float:
                result = left(variables) + right(variables)
                if not isfinite(result):
                    raise overflow()
                return result

            return add
        if op is ast.Sub:

            def sub(variables: Variables) -> float:
                result = left(variables) - right(variables)
                if not isfinite(result):
                    raise overflow()
                return result

            return sub
        if op is ast.Mult:

            def mul(variables: Variables) -> float:
                result = left(variables) * right(variables)
                if not isfinite(result):
                    raise overflow()
                return result

            return mul
        if op is ast.Pow:
            return lambda variables: _power(left(variables), right(variables), where)
        if op in (ast.Div, ast.FloorDiv, ast.Mod):
            divide: Callable[[float, float], float] = {
                ast.Div: lambda a, b: a / b,
                ast.FloorDiv: lambda a, b: a // b,
                ast.Mod: lambda a, b: a % b,
            }[op]

            def quotient(variables: Variables) -> float:
                a, b = left(variables), right(variables)
                if b == 0:
                    raise ExpressionError("division by zero", **where)
                result = divide(a, b)
                if not isfinite(result):
                    raise overflow()
                return result

            return quotient
        raise ExpressionError(f"operator {op.__name__} is not allowed", **where)

    def _boolop(self, node: ast.BoolOp, depth: int) -> Node:
        values = [self.compile(value, depth) for value in node.values]
        if isinstance(node.op, ast.And):

            def conjunction(variables: Variables) -> float:
                # Like Python: the first falsy operand, or the last one.
                result = 0.0
                for value in values:
                    result = value(variables)
                    if not result:
                        return result
                return result

            return conjunction

        def disjunction(variables: Variables) -> float:
            result = 0.0
            for value in values:
                result = value(variables)
                if result:
                    return result
            return result

        return disjunction

    def _compare(self, node: ast.Compare, depth: int) -> Node:
        for op in node.ops:
            if type(op) not in _COMPARISONS:
                raise ExpressionError(f"operator {_OPERATOR_SYMBOLS[type(op)]!r} is not allowed", **self.at(node))
        first = self.compile(node.left, depth)
        pairs = [
            (_COMPARISONS[type(op)], self.compile(comparator, depth))
            for op, comparator in zip(node.ops, node.comparators, strict=True)
        ]
        if len(pairs) == 1:
            compare, second = pairs[0]
            return lambda variables: float(compare(first(variables), second(variables)))

        def chain(variables: Variables) -> float:
            # Each middle operand is evaluated once, as in Python's a < b < c.
            left = first(variables)
            for compare, operand in pairs:
                right = operand(variables)
                if not compare(left, right):
                    return 0.0
                left = right
            return 1.0

        return chain

    def _ifexp(self, node: ast.IfExp, depth: int) -> Node:
        test = self.compile(node.test, depth)
        body = self.compile(node.body, depth)
        orelse = self.compile(node.orelse, depth)
        return lambda variables: body(variables) if test(variables) else orelse(variables)

    def _call(self, node: ast.Call, depth: int) -> Node:
        if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
            callee = node.func.id if isinstance(node.func, ast.Name) else ast.unparse(node.func)
            raise ExpressionError(
                f"cannot call {callee!r}; allowed functions are {', '.join(sorted(FUNCTIONS))}", **self.at(node)
            )
        name = node.func.id
        if node.keywords:
            raise ExpressionError(f"keyword arguments are not allowed in {name}()", **self.at(node.keywords[0]))
        lowest, highest, function = FUNCTIONS[name]
        count = len(node.args)
        # Refuse what an argument is made of before how many there are: it is the worse mistake.
        args = [self.compile(arg, depth) for arg in node.args]
        if count < lowest or (highest is not None and count > highest):
            wanted = f"{lowest}" if lowest == highest else f"{lowest} to {highest}" if highest else f"{lowest} or more"
            raise ExpressionError(f"{name}() takes {wanted} arguments, not {count}", **self.at(node))
        where = self.at(node)
        if count == 1:
            (only,) = args
            return lambda variables: function(only(variables), where=where)
        return lambda variables: function(*[arg(variables) for arg in args], where=where)
