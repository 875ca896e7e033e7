"""`hemicube`: the one command-line front for the twin, calibration and reconstruction. Each package
registers its own sub-commands (twin.cli, calibration.cli, reconstruction.cli); the main job, `validate`,
spans them and lives here."""
from __future__ import annotations

import argparse
import errno
import os
import sys

from twin.exitcodes import EXIT_CODES, EXIT_IO, EXIT_USAGE


def cmd_validate(args) -> int:
    from hemicube.junit import check_junit_path
    from hemicube.validate import run_suite, run_validation

    if args.junit is not None:
        check_junit_path(args.junit)
    if args.suite is not None:
        return run_suite(args.suite, rig=args.rig, device=args.device, output=args.output,
                         resolution=args.resolution, seed=args.seed, jobs=args.jobs, as_json=args.json,
                         frames=args.frames, junit=args.junit)
    return run_validation(rig=args.rig, sample=args.sample, device=args.device, as_json=args.json,
                          output=args.output, resolution=args.resolution, seed=args.seed,
                          progress=not args.no_progress, anyway=args.anyway, frames=args.frames, junit=args.junit)


EPILOG = "exit codes:\n" + "\n".join(f"  {k}  {v}" for k, v in EXIT_CODES.items())


def _version() -> str:
    """The installed package's version (pyproject.toml's, through the package metadata)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hemicube-twin")
    except PackageNotFoundError:
        return "(not installed: run `make setup` or `pip install -e .`)"


# the commands this module adds (each package's cli module has its own COMMANDS: PACKAGES)
COMMANDS = {"validate": "the main job: check the twin end to end and report", "bench": "benchmarks; print JSON"}
# the packages whose cli module adds commands to the front, in the order `--help` lists them: each has COMMANDS (their
# names and one-line help, light to import) and register(sub)
PACKAGES = ("twin.cli", "reconstruction.cli", "calibration.cli", "hemicube.design")


def _front() -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    p = argparse.ArgumentParser(prog="hemicube", description=__doc__, epilog=EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    return p, p.add_subparsers(dest="command", required=True)


def overview_parser() -> argparse.ArgumentParser:
    """The front alone: every command's name and help, none of their options. What `hemicube`, `hemicube --help` and
    `hemicube --version` parse with, so that they import no package's heavy modules (torch, Warp)."""
    import importlib

    p, sub = _front()
    for table in [importlib.import_module(m).COMMANDS for m in PACKAGES] + [COMMANDS]:
        for name, text in table.items():
            sub.add_parser(name, help=text)
    return p


def owner(command: str | None) -> tuple[str, ...]:
    """The packages whose register() a command needs: the one whose COMMANDS names it (none for this module's own
    `validate`; twin's and reconstruction's benches for `bench`), or every package for None or a name no package
    has (so that argparse's error lists every command)."""
    import importlib

    if command == "validate":
        return ()
    if command == "bench":
        return ("twin.cli", "reconstruction.cli")
    for m in PACKAGES:
        if command in importlib.import_module(m).COMMANDS:
            return (m,)
    return PACKAGES


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line with every command's options (each package's register), or with those of `command` alone
    (owner): a command imports only the packages it belongs to, so `hemicube rig info` loads neither torch nor Warp
    where `hemicube reconstruct` loads both."""
    import importlib

    packages = PACKAGES if command is None else owner(command)
    everything = packages == PACKAGES
    p, sub = _front()
    if command != "bench":
        for m in packages:
            importlib.import_module(m).register(sub)
    if everything or command == "validate":
        _add_validate(sub)
    if everything or command == "bench":
        bench = sub.add_parser("bench", help=COMMANDS["bench"]).add_subparsers(dest="bench_command", required=True)
        for m in ("twin.cli", "reconstruction.cli"):
            importlib.import_module(m).register_bench(bench)
    return p


def _add_validate(sub) -> None:
    """The main job's command and its options."""
    from twin.capture.plan import DEFAULT_FRAMES, DEFAULT_SEED, FRAMES_HELP

    s = sub.add_parser("validate", help=COMMANDS["validate"])
    s.add_argument("--rig", default="mini", help="built-in rig (paper, mini) or rig folder (default: %(default)s)")
    s.add_argument("--sample", default="ramps", help="built-in sample (`hemicube samples list`) or a folder of "
                   "OpenSVBRDF maps (default: %(default)s)")
    s.add_argument("--device", default="cpu", help="torch/Warp device: cpu, cuda, cuda:N (default: %(default)s)")
    s.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")
    s.add_argument("--junit", metavar="FILE", help="also write the checks and thresholds as JUnit XML (one test case "
                   "each; with --suite, one test suite a sample), the format CI systems read (docs/ci.md)")
    s.add_argument("--suite", nargs="*", metavar="NAME", help="validate every sample of the material suite, or "
                   "the samples named, in parallel, and print one table (default: one sample, --sample)")
    s.add_argument("--jobs", type=int, help="suite samples run at a time (default: the number of cores)")
    s.add_argument("-o", "--output", help="folder for the capture, the reconstruction and the report (default: "
                   "hemicube-validate/RIG_SAMPLE_seedSEED; with --suite, hemicube-validate/suite_RIG_seedSEED, "
                   "plus the samples' names for a run of other samples, holding one folder per sample and report/)")
    s.add_argument("--resolution", type=int, help="texture grid texels per side (default: the pipeline's, 48)")
    s.add_argument("--seed", type=int, default=DEFAULT_SEED, help="the virtual capture's seed (default: %(default)s)")
    s.add_argument("--frames", type=int, default=DEFAULT_FRAMES, help=FRAMES_HELP)
    s.add_argument("--no-progress", action="store_true", help="no progress output")
    s.add_argument("--anyway", action="store_true", help="on the CPU, run even a capture estimated to take "
                   "hours (the paper rig) instead of stopping with the estimate")
    s.set_defaults(func=cmd_validate)


# the way on from the operating system's refusals to write (the writers leave nothing half-written, twin.atomic; a
# capture or a reconstruction run again goes on from what it had finished)
_FULL = "free some space and run the command again (a capture or a reconstruction goes on from what it had finished)"
_NOT_OURS = "choose a folder you may write to"
_WAY_ON = {errno.EROFS: "choose a folder on a writable file system", errno.EACCES: _NOT_OURS, errno.EPERM: _NOT_OURS,
           errno.ENOSPC: _FULL, getattr(errno, "EDQUOT", errno.ENOSPC): _FULL}


def _os_error_line(e: OSError) -> str:
    """One line for an error of the operating system: the path, the cause in words, and the way on where the user
    has one (a read-only place, a full disk)."""
    cause = str(e.strerror or e)
    line = cause[:1].lower() + cause[1:]
    if e.filename is not None:
        line = f"{os.fsdecode(e.filename)}: {line}"
    way = _WAY_ON.get(e.errno)
    return f"{line}; {way}" if way else line


def _check_device(device) -> None:
    """A ValueError (one line) when this machine lacks `device`; the CPU is always there. Warp's own messages while it
    looks for CUDA (its C code writes them to the stderr file descriptor) are kept off: the error is the one line."""
    if device is None or device == "cpu":
        return
    from twin.optics.inputs import check_device

    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # a stream without a descriptor (a test's capture): nothing to hide
        check_device(device)
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), fd)
        check_device(device)
    finally:
        sys.stderr.flush()
        os.dup2(saved, fd)
        os.close(saved)


def main(argv: list[str] | None = None) -> int:
    """The `hemicube` command: `argv` its arguments without the program's name, a list of strings (default:
    sys.argv[1:]), e.g. main(["validate", "--rig", "mini"]). Returns the exit code (twin.exitcodes: 0 done, 1 a goal
    or threshold missed, 2 bad usage or input, 3 the system refused a read or a write); an input error is one line
    on stderr, no traceback. The commands print their results on stdout; option values are in the units their
    help states (mm, pixels, seconds)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), None)  # the front has no option that takes a value
    # a command: its options are needed, and only the package that has them; none: the front's overview alone
    args = (build_parser(command) if command else overview_parser()).parse_args(argv)  # bad usage: one line, exit 2
    try:
        # before any work: a device this machine lacks is one line; a command whose --device is another machine's
        # (the Ray batch commands': the cluster's, twin.batch) says so with device_here=False
        if getattr(args, "device_here", True):
            _check_device(getattr(args, "device", None))
        return args.func(args)
    except (ValueError, FileExistsError, FileNotFoundError, KeyError) as e:  # every input error is a ValueError
        print(f"hemicube: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as e:  # the system's own refusal (a read-only place, a full disk): one line; a traceback is for bugs
        print(f"hemicube: error: {_os_error_line(e)}", file=sys.stderr)
        return EXIT_IO


if __name__ == "__main__":
    sys.exit(main())
