"""Problems by name: the registry, the parameters of each problem, and the checks of its levels.

A problem solves one *level* (a mesh resolution) at a time and returns a record (a dict of
numbers); :func:`cutfem.run` (:mod:`cutfem.runs.runner`) solves a sequence of levels, times them,
and adds the rates between levels.  Problems come from three places: the modules of the
``problems`` package (registered on import), any module or script that uses :func:`register`, and
installed packages that declare an entry point in the group ``cutfem.problems`` (the entry point
names a module or a problem object to load).

A problem is either a :class:`Problem` subclass or a plain function decorated with
:func:`register`::

    from cutfem import register, Param

    @register("my-problem", levels=[0.2, 0.1, 0.05], level_name="spacing",
              params=[Param("tau_f", float, 0.1, "face stabilization", minimum=0)])
    def my_problem(level, tau_f):
        ...
        return {"h": h, "dofs": n, "l2_error": e}
"""

from __future__ import annotations

import importlib
import inspect
import math
import sys
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = [
    "Param",
    "Problem",
    "register",
    "get_problem",
    "available_problems",
    "check_levels",
    "ProblemError",
    "LazyFields",
]

#: the definition of ``h`` of a problem on a background tet mesh (cut problems) and on a surface
#: mesh (meshed problems), for a problem's ``definitions``; :data:`H_AXIS_LABELS` names them on a plot
H_BACKGROUND = "global mesh size: N**(-1/3), N the number of background nodes (the nodes of its tets)"
H_SURFACE = "global mesh size: N**(-1/2), N the number of surface nodes"
H_AXIS_LABELS = {H_BACKGROUND: "$h = N^{-1/3}$, $N$ background nodes", H_SURFACE: "$h = N^{-1/2}$, $N$ surface nodes"}

#: definitions of the record entries shared by every problem (a problem's own ``definitions`` add to them)
COMMON_DEFINITIONS = {
    "h": "global mesh size, not defined by the problem (the built-in problems define it as H_BACKGROUND or H_SURFACE: "
         "N**(-1/3) of the background nodes or N**(-1/2) of the surface nodes)",
    "dofs": "unknowns per component: the number of P1 nodes (active nodes of a cut, surface nodes of a mesh)",
}


class LazyFields(Mapping):
    """The fields of a level (name -> pyvista dataset), built on first access only: a run that
    writes no VTK and draws no picture does not pay for them."""

    def __init__(self, build: Callable[[], dict]):
        self._build, self._data = build, None

    def _fields(self) -> dict:
        if self._data is None:
            self._data = dict(self._build())
        return self._data

    def __getitem__(self, key):
        return self._fields()[key]

    def __iter__(self):
        return iter(self._fields())

    def __len__(self):
        return len(self._fields())


class ProblemError(ValueError):
    """Bad problem name or parameter value; the message lists what is allowed."""


@dataclass
class Param:
    """A named problem parameter: type (float, int, str, bool), default, help, optional choices and
    bounds.  ``nargs="+"`` makes it a list.

    Numbers must be finite (an int also integral: 2.5 is not read as 2, nor True as 1), at least
    ``minimum`` when given, and one of ``choices`` when given (numbers compared by value: 0.5 is
    one of (1.0, 0.5)); ``positive``: greater than 0 (a radius, a coefficient, a penalty that
    must not vanish).  ``files``: the parameter also takes the path of an existing file besides
    its ``choices`` (a surface mesh).  Objects that are neither strings nor numbers (a level set, a
    mesh) pass through from Python unchecked: the problem checks them.  ``only`` = (name, values),
    or a tuple of such conditions that must all hold:
    the parameter shapes the result only when the parameter ``name`` is one of ``values`` (the
    torus's radii with ``surface="torus"``); given with another, it is refused
    (:meth:`Problem.resolve`) rather than silently ignored."""

    name: str
    type: type = float
    default: Any = None
    help: str = ""
    choices: tuple | None = None
    minimum: float | None = None
    nargs: str | None = None
    files: bool = False
    only: tuple | None = None
    positive: bool = False

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def convert(self, value):
        """Convert (from a string or a Python value) and validate; raises ProblemError."""
        if self.nargs == "+":
            values = value if isinstance(value, (list, tuple)) else [value]
            return [self._one(v) for v in values]
        return self._one(value)

    def _one(self, value):
        if value is None:
            return None
        try:
            if self.type is bool and isinstance(value, str):
                if value.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError(value)
                v = value.lower() in ("true", "1", "yes")
            elif self.type is str or not isinstance(value, str) and not isinstance(value, (int, float, np.number)):
                v = value  # objects (level sets, meshes) pass through from Python
            elif self.type in (int, float) and isinstance(value, (bool, np.bool_)):
                raise TypeError(value)
            elif self.type is int and not isinstance(value, str):
                if not float(value).is_integer():
                    raise ValueError(value)
                v = int(value)
            else:
                v = self.type(value)
        except (TypeError, ValueError, OverflowError):
            raise ProblemError(f"{self.flag}: cannot read {value!r} as {self.type.__name__}") from None
        number = isinstance(v, (int, float)) and not isinstance(v, bool)
        if number and not math.isfinite(v):
            raise ProblemError(f"{self.flag}: {v} is not a finite number")
        if self.choices is not None and (number or isinstance(v, str)) and v not in self.choices:
            if not (self.files and isinstance(v, str)):
                raise ProblemError(f"{self.flag}: {v!r} is not one of {', '.join(map(str, self.choices))}")
            if not Path(v).is_file():
                raise ProblemError(f"{self.flag}: {v!r} is neither {', '.join(map(str, self.choices))} nor an existing file")
        if self.minimum is not None and number and v < self.minimum:
            raise ProblemError(f"{self.flag}: {v} must be a finite number >= {self.minimum}")
        if self.positive and number and not v > 0:
            raise ProblemError(f"{self.flag}: {v} must be a positive number")
        return v


class Problem:
    """Base class of a registered problem.

    Subclasses set ``name``, ``summary``, ``params`` (list of :class:`Param`), ``level_name`` and
    ``default_levels``, and implement :meth:`solve_level`, which returns a record dict with at least
    ``h``; error entries end in ``_error`` (defined in ``definitions``); timings go in
    ``record["time"]`` (stage -> seconds); ``components`` is the number of solution components.
    A record may carry ``"fields"``: a dict of pyvista datasets for VTK output (not saved to JSON).
    """

    name: str = ""
    summary: str = ""
    params: list = []
    level_name: str = "level"
    level_type: type = float
    default_levels: list = []
    #: number of solution components (each has ``dofs`` unknowns)
    components: int = 1
    #: record key -> its definition (every ``*_error`` key should have one), saved in the JSON
    definitions: dict = {}

    def solve_level(self, level, **params) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError

    def levels_for(self, levels, params: dict):
        """The levels to run for the resolved ``params``: ``levels`` as given, or the defaults when
        None; a problem whose parameters make some levels meaningless adapts the defaults or
        refuses (ProblemError) before the first level runs."""
        return self.default_levels if levels is None else levels

    # parameters
    def param_map(self) -> dict:
        return {p.name: p for p in self.params}

    def resolve(self, given: dict) -> dict:
        """Defaults filled in, values converted and validated; unknown names raise ProblemError."""
        allowed = self.param_map()
        unknown = [k for k in given if k not in allowed]
        if unknown:
            raise ProblemError(
                f"unknown parameter(s) {', '.join(unknown)} for problem {self.name!r}; allowed: "
                + ", ".join(p.name for p in self.params)
            )
        out = {p.name: p.default for p in self.params}
        for k, v in given.items():
            out[k] = allowed[k].convert(v)
        for k in given:
            failing = self._failing(allowed[k], out)
            if failing is not None:
                name, values = failing
                other = allowed[name].flag
                raise ProblemError(f"{allowed[k].flag} applies only with {other} {' or '.join(values)}, not with {other} "
                                   f"{out[name]!r}: leave {allowed[k].flag} out, or choose {other} {values[0]}")
        return out

    @staticmethod
    def _failing(param: "Param", params: dict):
        """The first condition (name, values) of ``param.only`` that ``params`` do not meet, or None."""
        only = param.only
        conditions = () if only is None else only if isinstance(only[0], tuple) else (only,)
        return next((c for c in conditions if not (isinstance(params[c[0]], str) and params[c[0]] in c[1])), None)

    @classmethod
    def _applies(cls, param: "Param", params: dict) -> bool:
        return cls._failing(param, params) is None

    def applicable(self, params: dict) -> dict:
        """The resolved ``params`` that shape this run: those without ``only``, or whose ``only``
        holds (the torus's radii for the torus, not for the sphere); what a record and a figure name."""
        pm = self.param_map()
        return {k: v for k, v in params.items() if k not in pm or self._applies(pm[k], params)}

    def describe(self) -> str:
        lines = [f"{self.name}: {self.summary}", f"  levels ({self.level_name}): default {self.default_levels}"]
        for p in self.params:
            extra = f" (one of {', '.join(map(str, p.choices))}{', or a file' if p.files else ''})" if p.choices else ""
            lines.append(f"  {p.flag} {p.type.__name__.upper()}{' ...' if p.nargs else ''}  {p.help}{extra} [default {p.default}]")
        return "\n".join(lines)


_REGISTRY: dict[str, Problem] = {}
_ORIGIN: dict[str, str] = {}  # name -> the module that registered it
_LOADED = False


def register(name=None, *, summary: str = "", params=None, levels=None, level_name: str = "level", level_type=float,
             definitions=None):
    """Register a problem class (a :class:`Problem` subclass) or a level function under ``name``.

    Used bare on a class (``@register``) it takes the class's ``name``.  On a function
    ``f(level, **params) -> record`` give ``name``, ``params``, ``levels``, ``level_name`` and
    ``definitions`` (record key -> its definition, as :attr:`Problem.definitions`: every
    ``*_error`` key, and ``dofs`` where it is not the nodes of one field).

    Registering a name again replaces the earlier problem (a notebook cell run twice), except a
    built-in problem's name, which raises ValueError: the built-ins are loaded first, so a problem
    of yours is never silently replaced by one of them.
    """

    def wrap(obj):
        _load_builtin_and_plugins()  # returns at once inside the load (the built-ins registering)
        if inspect.isclass(obj) and issubclass(obj, Problem):
            problem = obj()
            if isinstance(name, str):
                problem.name = name
        elif callable(obj):
            fn = obj

            class _FunctionProblem(Problem):
                def solve_level(self, level, **p):
                    return fn(level, **p)

            problem = _FunctionProblem()
            problem.name = name if isinstance(name, str) else fn.__name__.replace("_", "-")
            problem.summary = summary or (inspect.getdoc(fn) or "").split("\n")[0]
            problem.params = list(params or [])
            problem.default_levels = list(levels or [])
            problem.level_name = level_name
            problem.level_type = level_type
            problem.definitions = dict(definitions or {})
        else:
            raise TypeError("register() decorates a Problem subclass or a function f(level, **params)")
        if not problem.name:
            raise ValueError("a problem needs a name")
        if _is_builtin(_ORIGIN.get(problem.name, "")) and not _is_builtin(obj.__module__):
            raise ValueError(f"{problem.name!r} is the name of a built-in problem; register yours under another name")
        _REGISTRY[problem.name] = problem
        _ORIGIN[problem.name] = obj.__module__
        return obj

    if inspect.isclass(name) or (callable(name) and not isinstance(name, str)):
        obj, name = name, None
        return wrap(obj)
    return wrap


_LOAD_LOCK = threading.RLock()


def _is_builtin(module: str) -> bool:
    """Whether a problem defined in ``module`` comes with cutfem (:mod:`cutfem.problems`)."""
    return module.startswith("cutfem.problems.")


def _load_builtin_and_plugins():
    """Import the built-in problems and the plug-ins once.  Other threads wait for a load in
    progress (they saw an empty registry before: 'unknown problem' from two threads' first
    cutfem.run at once); the loading thread itself, re-entering through a problem module, does not."""
    global _LOADED
    if _LOADED == "done":
        return
    with _LOAD_LOCK:
        if _LOADED:  # done, or being done by this very thread
            return
        _LOADED = "loading"
        try:
            importlib.import_module("cutfem.problems")
            try:
                from importlib.metadata import entry_points

                for ep in entry_points(group="cutfem.problems"):
                    try:
                        ep.load()
                    except Exception as exc:  # a broken plug-in must not break the built-in problems
                        print(f"warning: could not load cutfem problem plug-in {ep.name!r}: {exc}", file=sys.stderr)
            except Exception:  # pragma: no cover - metadata unavailable
                pass
        except BaseException:
            _LOADED = False
            raise
        _LOADED = "done"


def available_problems() -> dict:
    """All registered problems by name (built-in, registered, and entry-point plug-ins)."""
    _load_builtin_and_plugins()
    return dict(sorted(_REGISTRY.items()))


def get_problem(name: str) -> Problem:
    problems = available_problems()
    if name not in problems:
        raise ProblemError(f"unknown problem {name!r}; available: {', '.join(problems)}")
    return problems[name]


def check_levels(problem: Problem, levels, source: str = "levels") -> list:
    """The levels converted to the problem's level type and checked: each a positive finite number
    (a positive integer for integer levels).  ``source`` names the input in the message: the
    parameter (``levels``) from Python, the flag (``--spacing``, ``--levels``, ``--n``) from the
    command line.  A level given twice is refused: its rate would compare a level with itself and its
    output files (named by level) would be written twice.  Raises ProblemError naming the source,
    the bad value and the fix."""
    if levels is None:
        levels = problem.default_levels
    levels = [levels] if isinstance(levels, (str, int, float)) else list(levels)
    if not levels:
        raise ProblemError(f"{source}: no levels given for problem {problem.name!r}; give e.g. {problem.default_levels}")
    kind = "positive integer" if problem.level_type is int else "positive finite number"
    out = []
    for v in levels:
        try:
            x = problem.level_type(v) if isinstance(v, str) else v
            if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
                raise TypeError
            ok = math.isfinite(x) and x > 0 and (problem.level_type is not int or float(x) == int(x))
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise ProblemError(
                f"{source}: {problem.level_name} {v!r} is not a {kind}; give {problem.level_name} values like {problem.default_levels}"
            )
        out.append(int(x) if problem.level_type is int else x)
    seen = set()
    for x in out:
        if x in seen:
            raise ProblemError(
                f"{source}: {problem.level_name} {x!r} is given more than once; give each level once (the rates compare "
                "successive levels and the output files are named by level). To time a level again, run it again."
            )
        seen.add(x)
    return out
