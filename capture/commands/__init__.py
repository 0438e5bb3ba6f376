"""Sub-commands of `mca`: each module here exposes `register(app: typer.Typer) -> None`.

Modules are discovered by name, so adding a command never touches another
command's file. Keep imports of heavy libraries inside the command functions
so that `mca --help` stays fast.
"""
