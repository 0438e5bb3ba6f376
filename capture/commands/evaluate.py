"""`mca evaluate`: the simulated paper scenes as the paper's Table 2, or rendered real scenes scored per pixel (--rgbd)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer


def register(app: typer.Typer) -> None:
    @app.command("evaluate")
    def evaluate(
        scene: str = typer.Option("all", "--scene", "-s", help="paper-a .. paper-g, or 'all'."),
        profile: str = typer.Option("paper-70d", "--profile", "-p", help="Built-in profile name or TOML file."),
        scale: float = typer.Option(
            1.0,
            "--scale",
            help="Render size as a fraction of the profile's sensor "
            "(1.0 = the full 20 MP; smaller is faster, less precise).",
        ),
        seed: int = typer.Option(0, "--seed", help="Seed of the simulated sensor noise."),
        renders: str = typer.Option(
            None,
            "--renders",
            help="Table 2: read the scenes from this folder of `mca simulate` renders (CR2 + truth/), rendering "
            "and writing there the ones missing (a cache: same scale and seed).",
        ),
        peers: bool = typer.Option(
            True,
            "--peers/--no-peers",
            help="Also run the peers (Table 2: StereoSGBM, integer WTA; --rgbd: WTA, Bando).",
        ),
        rgbd: str = typer.Option(
            None,
            "--rgbd",
            help="A folder of rendered real scenes (mca simulate --from-rgbd-tree ...; its subfolders too): "
            "per-pixel figures of the pipeline, run as mca process runs it, and the peers.",
        ),
        bando: str = typer.Option(
            None, "--bando", help="--rgbd: Bando et al. 2008's built program (default: $MCA_BANDO_BIN)."
        ),
        as_json: bool = typer.Option(False, "--json", help="Print the figures as JSON (Table 2 or --rgbd)."),
        json_file: str = typer.Option(None, "--json-file", help="Also write the JSON figures to this file."),
        keep_outputs: str = typer.Option(
            None, "--keep-outputs", help="--rgbd: keep mca process's output folders here."
        ),
        only: str = typer.Option(None, "--only", help="--rgbd: only these renders or scenes (comma-separated)."),
    ) -> None:
        """Table 2 (default): render each paper scene with the simulator (noise, Bayer mosaic), run the pipeline
        and print per object the true and estimated inter-object depth with absolute and relative errors, the
        region count and whether the front-to-back order is right, beside the peers run on the same planes.

        --rgbd DIR: every rendered real scene under DIR through the pipeline exactly as `mca process` runs it,
        scored per pixel (bad-1, bad-0.5, the same near depth edges, depth error, relative inter-object error,
        coverage) beside the colour-line WTA and Bando 2008's program; per scene, then median and worst."""
        from mca.capture.evaluation_app import EvaluateError

        try:
            if rgbd is not None:
                _rgbd(rgbd, peers, bando, as_json, keep_outputs, only, json_file)
            else:
                _table2(profile, scene, scale, seed, renders, peers, as_json, json_file)
        except EvaluateError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None


def _say(text: str) -> None:
    typer.echo(text, err=True)


def _table2(
    profile: str,
    scene: str,
    scale: float,
    seed: int,
    renders: str | None,
    peers: bool,
    as_json: bool,
    json_file: str | None,
) -> None:
    from mca.capture.evaluation_app import evaluate_table2, format_table2, table2_document, table2_heading
    from mca.capture.outputs import write_json

    cache = Path(renders) if renders is not None else None
    run = evaluate_table2(profile, scene, scale=scale, seed=seed, renders=cache, peers=peers, on_progress=_say)
    if as_json or json_file is not None:
        document = table2_document(run.evaluations, run.methods, run.profile_name, run.optics, scale, seed)
        if json_file is not None:
            write_json(json_file, document)
        if as_json:
            typer.echo(json.dumps(document, indent=2))
            return
    typer.echo(table2_heading(run))
    typer.echo(format_table2(run))


def _rgbd(
    root: str,
    peers: bool,
    bando: str | None,
    as_json: bool,
    keep_outputs: str | None,
    only: str | None,
    json_file: str | None,
) -> None:
    from mca.capture.evaluation_app import RGBD_LEGEND, evaluate_rgbd_folder, format_rgbd, rgbd_document
    from mca.capture.outputs import write_json

    def finished(row: Any) -> None:
        parts = [f"{m} bad-1 {100 * row.metrics[m].bad_1:.1f}%" for m in row.metrics]
        _say(f"  {'; '.join(parts) or 'no result'}")

    wanted = tuple(s for s in only.split(",") if s) if only else None
    run = evaluate_rgbd_folder(
        root, peers=peers, bando=bando, keep_outputs=keep_outputs, only=wanted, on_row=finished, on_progress=_say
    )
    _say(f"evaluated {len(run.rows)} render(s) in {run.seconds:.0f} s")
    if json_file is not None:
        write_json(json_file, rgbd_document(run))
    if as_json:
        typer.echo(json.dumps(rgbd_document(run), indent=2))
        return
    typer.echo(RGBD_LEGEND)
    typer.echo(format_rgbd(run))
