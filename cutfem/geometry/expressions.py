"""The safe parser of a level set written as text (:meth:`~cutfem.geometry.levelset.FunctionLevelSet.from_expression`).

The text is parsed as a Python expression and its tree checked before anything is evaluated: only
numbers, the coordinates ``x, y, z``, the constants ``pi`` and ``e``, the operators ``+ - * / **``
and a list of numpy functions called with positional arguments pass.  The checked tree is compiled
and evaluated with no builtins in reach, on whole arrays or on interval enclosures
(:mod:`cutfem.geometry.intervals`, for the band search).  Small integer powers become repeated
multiplications and the other integer literals floats, so constants are computed in floating point.
"""

from __future__ import annotations

import numpy as np

from .intervals import Interval

__all__ = ["expression_function"]


#: numpy functions allowed in a text expression (FunctionLevelSet.from_expression)
_EXPRESSION_FUNCTIONS = {
    name: getattr(np, name)
    for name in ("sin", "cos", "tan", "arcsin", "arccos", "arctan", "arctan2", "sinh", "cosh", "tanh",
                 "exp", "log", "log2", "log10", "sqrt", "cbrt", "abs", "hypot", "minimum", "maximum")
}
#: the number of arguments of each function: numpy reads one more as the array to write into
_EXPRESSION_ARITY = {name: 2 if name in ("arctan2", "hypot", "minimum", "maximum") else 1 for name in _EXPRESSION_FUNCTIONS}
_EXPRESSION_CONSTANTS = {"pi": np.pi, "e": np.e}
_EXPRESSION_MAX_LENGTH = 10000


def _integer_power(a, n: int):
    """a**n for an integer 2 <= n <= 16 by repeated squaring (a few multiplications instead of the
    much slower general pow; the result differs from pow by a few ulp at most)."""
    result, base = None, a
    while n:
        if n & 1:
            result = base if result is None else result * base
        n >>= 1
        if n:
            base = base * base
    return result


def _integer_powers_transformer():
    import ast

    class IntegerPowers(ast.NodeTransformer):
        """Rewrite ``a ** n`` with an integer literal 2 <= n <= 16 into ``_integer_power(a, n)``; every
        other integer literal becomes a float, so that the constants are computed in floating point
        ('9**9**9' overflows at once instead of building a 370-million-digit integer)."""

        def visit_BinOp(self, node):
            exponent = node.right
            if isinstance(node.op, ast.Pow) and isinstance(exponent, ast.Constant) \
                    and type(exponent.value) is int and 2 <= exponent.value <= 16:
                return ast.Call(ast.Name("_integer_power", ast.Load()), [self.visit(node.left), exponent], [])
            return self.generic_visit(node)

        def visit_Constant(self, node):
            if type(node.value) is not int:
                return node
            try:
                return ast.copy_location(ast.Constant(float(node.value)), node)
            except OverflowError:  # its own message must not format the integer as a float either
                digits = int(node.value.bit_length() * 0.30102999566398120) + 1
                raise ValueError(f"the integer of about {digits} digits in the level-set expression is too large for a "
                                 "float (at most about 1.8e308): write a smaller number") from None

    return IntegerPowers()


def expression_function(text):
    """A vectorized f(x) for the expression ``text`` in x, y, z; ValueError for anything not allowed."""
    import ast

    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"a level-set expression must be a non-empty string in x, y, z, got {text!r}")
    if len(text) > _EXPRESSION_MAX_LENGTH:
        raise ValueError(f"the level-set expression is longer than {_EXPRESSION_MAX_LENGTH} characters; use a Python file")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        raise ValueError(
            f"cannot parse the level-set expression {text!r}: {exc.msg}; write it in Python syntax, "
            "e.g. 'x**2 + y**2 + z**2 - 1'"
        ) from None
    except (RecursionError, MemoryError):
        raise ValueError("the level-set expression is nested too deeply to be parsed; write it in a Python file "
                         "(FunctionLevelSet.from_file)") from None
    called = {id(node.func) for node in ast.walk(tree) if isinstance(node, ast.Call)}
    operators = (ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow, ast.USub, ast.UAdd)
    variables = {"x", "y", "z"} | set(_EXPRESSION_CONSTANTS)
    for node in ast.walk(tree):
        if isinstance(node, (ast.Expression, ast.Load) + operators):
            continue
        if isinstance(node, ast.BitXor):
            raise ValueError(f"the level-set expression {text!r} uses ^, which is not a power in Python: write ** (x**2)")
        if isinstance(node, (ast.BinOp, ast.UnaryOp)):
            continue  # the operator itself is checked as its own node
        if isinstance(node, ast.Constant) and type(node.value) in (int, float):
            continue
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in _EXPRESSION_FUNCTIONS or node.keywords:
                raise ValueError(
                    f"the level-set expression {text!r} calls {ast.unparse(node)!r}, which is not allowed; "
                    f"the functions are {', '.join(_EXPRESSION_FUNCTIONS)} with positional arguments"
                )
            arity = _EXPRESSION_ARITY[node.func.id]
            if len(node.args) != arity or any(isinstance(a, ast.Starred) for a in node.args):
                raise ValueError(
                    f"the level-set expression {text!r} calls {node.func.id} with {len(node.args)} argument(s) in "
                    f"{ast.unparse(node)!r}; {node.func.id} takes {arity}"
                )
            continue
        if isinstance(node, ast.Name):
            if node.id in _EXPRESSION_FUNCTIONS and id(node) not in called:
                raise ValueError(f"the level-set expression {text!r} uses the function {node.id} without calling it; "
                                 f"write {node.id}(...)")
            if node.id in variables or node.id in _EXPRESSION_FUNCTIONS:
                continue
            raise ValueError(
                f"the level-set expression {text!r} uses the unknown name {node.id!r}; it may use x, y, z, "
                f"pi, e and the functions {', '.join(_EXPRESSION_FUNCTIONS)}"
            )
        raise ValueError(
            f"the level-set expression {text!r} contains {ast.unparse(node) or type(node).__name__!r} ({type(node).__name__}), "
            "which is not allowed: use numbers, x, y, z, pi, e, + - * / ** and the listed numpy functions"
        )
    try:
        tree = ast.fix_missing_locations(_integer_powers_transformer().visit(tree))
        code = compile(tree, "<level-set expression>", "eval")
    except (RecursionError, MemoryError):
        raise ValueError("the level-set expression is nested too deeply to be compiled; write it in a Python file "
                         "(FunctionLevelSet.from_file)") from None

    def expression(x):
        if not isinstance(x, Interval):  # intervals: the band search's enclosures (cutfem.geometry.intervals)
            x = np.asarray(x, dtype=float)
        names = {"__builtins__": {}, **_EXPRESSION_FUNCTIONS, **_EXPRESSION_CONSTANTS, "_integer_power": _integer_power,
                 "x": x[..., 0], "y": x[..., 1], "z": x[..., 2]}
        with np.errstate(all="ignore"):  # NaN/inf values are reported by the callers, with the points
            try:
                out = eval(code, names)  # noqa: S307 - the tree was checked above
            except ArithmeticError as exc:  # constants alone: '1/0', '10.0**400' (arrays give inf or NaN)
                raise ValueError(f"the level-set expression {text!r} cannot be evaluated: {exc} in its constants") from None
        if isinstance(x, Interval):
            return out
        if np.iscomplexobj(out):  # '(-8)**(1/3)': Python's power of a negative number is complex
            raise ValueError(f"the level-set expression {text!r} gives complex values (a negative number to a fractional "
                             "power?); a level set is real: write cbrt(-8) or -(8**(1/3))")
        return np.broadcast_to(np.asarray(out, dtype=float), x.shape[:-1]).copy()

    return expression
