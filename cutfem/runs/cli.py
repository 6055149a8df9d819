"""The ``cutfem`` command.

    cutfem --version
    cutfem list
    cutfem run PROBLEM [--param value ...] [--levels L1 L2 ...] [--json PATH|-] [--vtk DIR] [--plot PATH]
    cutfem reproduce [--out DIR] [--full]

Errors in the input (an unknown problem or parameter, a bad value, an open surface file, a level
set that misses the box, a size that cannot fit in memory, ...) print one line and exit with
status 2; ``--debug`` shows the traceback.  The levels and the output paths (``--json``, ``--plot``,
``--vtk``: parent folder writable, extension known) are checked before anything is solved.  When a
level fails after others finished, the table and the JSON are still written with the finished
levels and the failure (level, error type, message), and the exit status is 2 (1 for an
unexpected error, which is a bug).  Existing files at the output paths are replaced; ``--plot``
writes nothing (and says so) when the records carry no finite positive errors to plot, ``--vtk`` nothing when they
carry no fields.

Under an MPI launcher (``mpiexec -n N cutfem run poisson-cut ...``) every rank solves the problem's
distributed levels (:mod:`cutfem.distributed`) and rank 0 alone prints and writes; a problem that
is not distributed is refused on more than one rank.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from contextlib import contextmanager
from pathlib import Path

from ..distributed.launch import launched_rank

__all__ = ["main", "entry"]


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's default exits with a usage dump; keep it short and useful
        raise SystemExit(_fail(f"{self.prog}: {message}"))


def _fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def _cmd_list(args) -> int:
    from .registry import available_problems

    for name, problem in available_problems().items():
        print(problem.describe() if args.verbose else f"{name:28s} {problem.summary}")
        if args.verbose:
            print()
    if not args.verbose:
        print("\n'cutfem list -v' shows the parameters; 'cutfem run PROBLEM --help' those of one problem.")
    return 0


def _problem_parser(problem) -> argparse.ArgumentParser:
    p = _Parser(prog=f"cutfem run {problem.name}", description=problem.summary, allow_abbrev=False)
    levels = p.add_mutually_exclusive_group()  # both given: refused, not the last one silently kept
    levels.add_argument("--levels", nargs="+", default=None, help=f"the {problem.level_name} of each level (default {problem.default_levels})")
    if problem.level_name not in {q.name for q in problem.params}:
        levels.add_argument("--" + problem.level_name.replace("_", "-"), dest="levels", nargs="+", default=None, help="same as --levels")
    for q in problem.params:
        extra = f" (one of {', '.join(map(str, q.choices))}{', or a file' if q.files else ''})" if q.choices else ""
        p.add_argument(q.flag, dest=q.name, default=None, nargs=q.nargs, metavar=q.type.__name__.upper(), help=f"{q.help}{extra} [default {q.default}]")
    p.add_argument("--json", default=None, metavar="PATH", help="write the results as JSON ('-' for standard output)")
    p.add_argument("--vtk", default=None, metavar="DIR", help="write the fields of every level as VTK files for ParaView")
    p.add_argument("--plot", default=None, metavar="PATH", help="write a convergence plot (PNG or PDF)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    return p


def _join_negative_values(argv, problem):
    """'--box -1,-1,-1,1,1,1' -> '--box=-1,-1,-1,1,1,1', '--surface "-(x**2 + y**2 + z**2) + 1"' ->
    '--surface=-(x**2 + ...)': argparse would read a value with a leading minus as an option.  A
    value that starts with '-' and a digit or '.' is a number; for a text parameter (a surface
    expression) any value with one leading '-' is taken, except '-h' (help)."""
    single = {q.flag for q in problem.params if q.nargs is None}
    text = {q.flag for q in problem.params if q.nargs is None and q.type is str}

    def negative(flag, value):
        if value[:1] != "-" or value.startswith("--") or value == "-h":
            return False
        return value[1:2].isdigit() or value[1:2] == "." or flag in text

    out, i = [], 0
    while i < len(argv):
        tok = argv[i]
        if tok in single and i + 1 < len(argv) and negative(tok, argv[i + 1]):
            out.append(f"{tok}={argv[i + 1]}")
            i += 2
            continue
        out.append(tok)
        i += 1
    return out


#: extensions of --json and --plot
JSON_SUFFIXES = (".json",)
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
#: the errors of bad input or of a size or problem that cannot be solved: one line, status 2
INPUT_ERRORS = (ValueError, FileNotFoundError, RuntimeError, OSError, MemoryError)


def _level_flag(argv, problem) -> str:
    """The flag the levels were given with, for messages: --levels or --<level name>."""
    own = "--" + problem.level_name.replace("_", "-")
    for tok in argv:
        if tok in ("--levels", own) or tok.startswith(("--levels=", own + "=")):
            return tok.split("=", 1)[0]
    return "--levels"


def _cmd_run(argv) -> int:
    from .registry import ProblemError, check_levels, get_problem
    from .runner import check_output, run

    if not argv or argv[0].startswith("-"):
        raise ProblemError("usage: cutfem run PROBLEM [--param value ...]; 'cutfem list' shows the problems")
    problem = get_problem(argv[0])
    parser = _problem_parser(problem)
    allowed = ", ".join(["--levels"] + [q.flag for q in problem.params] + ["--json", "--vtk", "--plot", "--quiet", "--debug"])
    known, unknown = parser.parse_known_args(_join_negative_values(argv[1:], problem))
    if unknown:
        raise ProblemError(f"unknown argument(s) {' '.join(unknown)} for {problem.name}; allowed: {allowed}")
    if launched_rank() != 0:  # under mpiexec every rank solves, rank 0 alone reports and writes
        known.quiet, known.json, known.plot, known.vtk = True, None, None, None
    params = {q.name: getattr(known, q.name) for q in problem.params if getattr(known, q.name) is not None}
    # None when not given: run() then asks the problem for its defaults under these parameters
    levels = None if known.levels is None else check_levels(problem, known.levels, _level_flag(argv, problem))
    to_stdout = known.json == "-"
    if known.json and not to_stdout:
        check_output("--json", known.json, JSON_SUFFIXES)
    if known.plot:
        check_output("--plot", known.plot, PLOT_SUFFIXES)
    if known.vtk:
        check_output("--vtk", known.vtk, folder=True)
    with _warnings_as_lines(progress=not (known.quiet or to_stdout)):
        result = run(
            problem.name, levels=levels, progress=not (known.quiet or to_stdout), keep_finished=True,
            command=["cutfem", "run", *argv], keep_fields=bool(known.vtk), **params,
        )
    if to_stdout:
        print(result.dumps())
    elif result.records and launched_rank() == 0:
        print(result.table())
    if known.json and not to_stdout:
        Path(known.json).parent.mkdir(parents=True, exist_ok=True)
        Path(known.json).write_text(result.dumps())
        print(f"wrote {known.json}", file=sys.stderr)
    if known.vtk and result.records:
        out = Path(known.vtk)
        out.mkdir(parents=True, exist_ok=True)
        series = {}
        for index, (level, rec) in enumerate(zip(result.levels, result.records)):
            for kind, ds in rec.get("fields", {}).items():
                ext = ".vtp" if ds.__class__.__name__ == "PolyData" else ".vtu"
                path = out / f"{problem.name}_{problem.level_name}{level}_{kind}{ext}"
                ds.save(path)
                series.setdefault(kind, []).append((index, path.name))
        for kind, entries in series.items():
            write_pvd(out / f"{problem.name}_{kind}.pvd", entries)
        if series:
            print(f"wrote VTK files and one .pvd series over the levels per field to {out}", file=sys.stderr)
        else:
            print(f"--vtk: nothing written: the records of {problem.name} carry no fields (a record's \"fields\")",
                  file=sys.stderr)
    from .convergence import plotted_keys

    if known.plot and result.records and not plotted_keys(result):  # an empty figure would pass for a result
        why = ("no errors (no exact solution for this input)" if not result.error_keys() else
               f"no finite positive errors ({', '.join(result.error_keys())} NaN, infinite or zero at every level)")
        print(f"--plot: nothing written: the records of {problem.name} carry {why} to plot against h; an existing "
              f"{known.plot} is left as it was", file=sys.stderr)
    elif known.plot and result.records:
        from .convergence import convergence_plot

        Path(known.plot).parent.mkdir(parents=True, exist_ok=True)
        convergence_plot(result, known.plot)
        print(f"wrote {known.plot}", file=sys.stderr)
    if result.failure is None:
        return 0
    if known.debug:
        raise result.exception
    f = result.failure
    done = f" ({f['index']} finished level(s) kept)" if f["index"] else ""
    _fail(f"{problem.level_name}={f['level']} failed{done}: {f['message']}")
    return 2 if isinstance(result.exception, INPUT_ERRORS) else 1


@contextmanager
def _warnings_as_lines(progress: bool):
    """Within the context, a warning (a parameter that costs accuracy, a solver that needed many
    iterations) prints as one line ``warning: ...`` on standard error, on a line of its own after
    an open progress line, instead of Python's file, line number and source line."""
    def show(message, category, filename, lineno, file=None, line=None):
        print(f"{chr(10) if progress else ''}warning: {message}", file=sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield


def write_pvd(path, entries) -> None:
    """A ParaView collection (.pvd) of the files ``entries`` = [(step, file name relative to the
    .pvd), ...]: the levels of a run become the time steps 0, 1, 2, ... of one series."""
    rows = "\n".join(f'    <DataSet timestep="{step}" part="0" file="{name}"/>' for step, name in entries)
    Path(path).write_text(
        '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
        f"{rows}\n  </Collection>\n</VTKFile>\n"
    )


def _cmd_reproduce(argv) -> int:
    from ..studies.reproduce import main as reproduce_main

    return reproduce_main(argv)


def main(argv=None) -> int:
    """Run the ``cutfem`` command with ``argv`` (default: the process's arguments); returns the exit status.

    ``run`` solves inside :func:`cutfem.memory.large_run`, as :func:`cutfem.run` does from a script
    (``CUTFEM_ALLOCATOR=system`` keeps the system's allocation defaults).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    parser = _Parser(prog="cutfem", description="unfitted finite element methods on surfaces: problems, runs, studies")
    parser.add_argument("command", choices=["list", "run", "reproduce"], help="list the problems, run one, or reproduce the paper")
    parser.add_argument("--version", action="store_true", help="print the version of cutfem")
    if argv and argv[0] == "--version":
        from .. import __version__

        print(f"cutfem {__version__}")
        return 0
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        print("\ncommands:\n  list [-v]                 the registered problems\n  run PROBLEM [options]     solve at several levels, print rates"
              "\n  reproduce [--out DIR] [--full]   every figure and table of the paper")
        return 0
    command, rest = argv[0], argv[1:]
    try:
        if command == "list":
            lp = _Parser(prog="cutfem list")
            lp.add_argument("-v", "--verbose", action="store_true")
            return _cmd_list(lp.parse_args(rest))
        if command == "run":
            if rest[:1] in (["-h"], ["--help"]):
                print("usage: cutfem run PROBLEM [--levels L ...] [--param value ...] [--json PATH] [--vtk DIR] [--plot PATH]\n\n"
                      "'cutfem list' shows the problems, 'cutfem run PROBLEM --help' the parameters of one.")
                return 0
            if len(rest) >= 2 and rest[1] in ("-h", "--help"):
                from .registry import get_problem

                _problem_parser(get_problem(rest[0])).print_help()
                return 0
            return _cmd_run(rest)
        if command == "reproduce":
            return _cmd_reproduce(rest)
        return _fail(f"unknown command {command!r}; use list, run or reproduce")
    except SystemExit as exc:
        return int(exc.code or 0)
    except INPUT_ERRORS as exc:
        if debug:
            raise
        return _fail(str(exc))


def entry() -> None:
    """The ``cutfem`` console command: :func:`main` on the process's arguments, then exit.

    Before the interpreter's teardown, every object still alive is moved out of the cyclic
    collector's reach (``gc.freeze``): the final collections of the teardown would otherwise
    traverse numba's type registries and the run's objects once more, for nothing (the process's
    memory goes back to the system as a whole).  That collection took 0.09-0.25 s of each run of
    ``cutfem run mean-curvature-cut --spacing 0.0125`` (0.14-0.31 s from the end of the run to
    the end of the process, against 0.05-0.06 s with the freeze).  :func:`main` itself, called
    in-process (tests, scripts), does not do this: a live process keeps collecting.
    """
    import gc

    status = main()
    gc.freeze()
    sys.exit(status)


if __name__ == "__main__":  # pragma: no cover
    entry()
