"""The `mca` command line: a typer app assembled from the modules in `capture.commands`."""

from __future__ import annotations

import gc
import importlib
import os
import pkgutil

import typer

from mca.capture import commands

# Nothing leaves the bench: rerun's SDK and viewer send no usage analytics from any `mca` process.
os.environ.pop("FORCE_RERUN_ANALYTICS", None)
os.environ.setdefault("RERUN_ANALYTICS", "0")
os.environ.setdefault("TELEMETRY_ENABLED", "false")

HELP_OPTIONS = {"help_option_names": ["-h", "--help"]}  # -h as well as --help, on every command

app = typer.Typer(
    name="mca",
    help="Accurate-depth 3D imaging from one multi-colour-filter-aperture photograph.",
    no_args_is_help=True,
    add_completion=True,  # --install-completion / --show-completion for bash, zsh, fish
    pretty_exceptions_enable=False,
    # Help texts are plain text: rich markup would turn "usb:BUS:ADDR" into "usb🚌ADDR" (its :bus: emoji code).
    rich_markup_mode=None,
    context_settings=HELP_OPTIONS,
)


def _print_version(value: bool) -> None:
    if value:
        from mca import __version__

        typer.echo(f"mca {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", "-V", help="Print the version and exit.", callback=_print_version, is_eager=True
    ),
) -> None:
    """Accurate-depth 3D imaging from one multi-colour-filter-aperture photograph."""


def _register_commands() -> None:
    for module_info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{commands.__name__}.{module_info.name}")
        register = getattr(module, "register", None)
        if register is not None:
            register(app)


_register_commands()


def main() -> None:
    try:
        app()
    finally:
        forget_handled_interrupt()
        skip_last_collection()


def skip_last_collection() -> None:
    """Spare the interpreter the garbage collection it makes while it shuts down, once the command is done.

    That last collection walks every object still alive, and a command that processed a capture leaves about
    125,000 (numba's compiler, OpenCV, rich): 0.19 s of a 20 MP `mca process`'s exit of 0.29 s (docs/speed.md).
    Frozen objects are not walked. Nothing of ours needs that collection: every output is written, closed and
    renamed into place before its command returns, and what must run at exit (rerun's flush, temporary folders'
    removal, logging's flush) is registered with `atexit`, which still runs."""
    gc.freeze()


def forget_handled_interrupt() -> None:
    """Let a Ctrl-C that a command caught and reported end the process with the command's own exit code.

    CPython marks an interrupt as unhandled when a KeyboardInterrupt leaves code run by `exec` or `eval` on a
    string (dataclasses and numba make functions that way), even when a caller catches it further up. Under
    `python -m mca` the mark survives `sys.exit`: the process then ends by killing itself with SIGINT (return
    code -2, shell status 130) instead of, say, `mca process`'s exit 1 after it listed the interrupted files.
    Running a string clears the mark. An interrupt that really is unhandled is marked again after this, on
    its way out of the module."""
    exec("pass")  # a constant string, run for its side effect on that mark


if __name__ == "__main__":
    main()
