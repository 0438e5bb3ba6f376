"""`mca review DIR`: a table of the results and recordings in an output folder: shot, time, regions, distances, status.

The rows come from `capture.review` (it never imports rerun, so this is instant even on a large folder).
"""

from __future__ import annotations

import json
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("review")
    def review(
        directory: Path = typer.Argument(..., metavar="DIR", help="An output folder of `mca process`."),
        as_json: bool = typer.Option(False, "--json", help="Print the rows as one JSON list."),
    ) -> None:
        """List the results and recordings in DIR: shot, time, regions, nearest and farthest object, status."""
        from mca.capture.review import format_table, review_document, review_notes, review_rows

        if not directory.is_dir():
            typer.echo(f"error: {directory} is not a folder; give the --out folder of `mca process`", err=True)
            raise typer.Exit(2)
        rows = review_rows(directory)
        if as_json:
            typer.echo(json.dumps(review_document(rows), indent=2))
            return
        if not rows:
            typer.echo(f"{directory}: no results (*/result.json) and no recordings (*.rrd) here")
            return
        typer.echo(format_table(rows))
        for line in review_notes(rows):
            typer.echo(line)
