"""`mca process`: photographs in, depth maps, regions, layers and 3D scenes out (locally, in parallel or on Dask)."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("process")
    def process(
        inputs: list[Path] = typer.Argument(
            ..., metavar="INPUT...", help="Photographs (CR2, DNG, TIFF, PNG, JPEG, PPM) or folders of them."
        ),
        out: Path | None = typer.Option(
            None,
            "--out",
            "-o",
            help="Output folder; each input gets OUT/<stem>/ "
            "(default: output_dir of the config file, see `mca config show`).",
        ),
        profile: str | None = typer.Option(
            None,
            "--profile",
            "-p",
            help="Built-in profile name or TOML file (default: the config file's, else paper-70d); "
            "'none' = filter geometry only, disparities in pixels.",
        ),
        workers: int | None = typer.Option(
            None, "--workers", "-j", min=1, help="Files processed in parallel on this machine (default: config, 1)."
        ),
        force: bool = typer.Option(False, "--force", help="Redo inputs whose output folder is already finished."),
        quality: str = typer.Option(
            "full",
            "--quality",
            metavar="full|preview",
            help="full: the evaluated settings; preview: faster, coarser regions for live use (recorded in "
            "result.json; a preview result is never taken for a full one).",
        ),
        watch: bool = typer.Option(False, "--watch", help="Keep processing files as they arrive in the folders."),
        watch_timeout: float | None = typer.Option(
            None, "--watch-timeout", metavar="S", help="With --watch: stop after S seconds with nothing new."
        ),
        poll_interval: float = typer.Option(
            1.0, "--poll-interval", metavar="S", help="With --watch: seconds between looks at the folders."
        ),
        settle: float = typer.Option(
            2.0, "--settle", metavar="S", help="With --watch: take a file once unchanged for S seconds."
        ),
        record: Path | None = typer.Option(
            None, "--record", metavar="FILE.rrd", help="Record every shot (rerun); merged into FILE.rrd at the end."
        ),
        serve: bool = typer.Option(
            False,
            "--serve",
            help="Stream every shot to a rerun web viewer while processing (one file at a "
            "time); keeps serving until Ctrl-C.",
        ),
        bind: str = typer.Option(
            "127.0.0.1",
            "--bind",
            metavar="ADDRESS",
            help="With --serve: address the viewer listens on; only an explicit "
            "non-loopback address opens it to the network.",
        ),
        cluster: str | None = typer.Option(
            None,
            "--cluster",
            metavar="tcp://HOST:8786",
            help="Run on a Dask distributed scheduler (shared filesystem).",
        ),
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress, only the summary."),
        as_json: bool = typer.Option(
            False, "--json", help="Print one JSON object (every file's outcome and totals) instead of the table."
        ),
        max_megapixels: float | None = typer.Option(
            None,
            "--max-megapixels",
            metavar="MP",
            help="Refuse inputs larger than MP megapixels before decoding them "
            "(default: $MCA_MAX_MEGAPIXELS, else 100).",
        ),
    ) -> None:
        """Process photographs into OUT/<stem>/: depth.tiff, regions.png, result.json, all_in_focus.png, layers/,
        scene.ply and scene.glb (docs/outputs.md). Finished folders are skipped unless --force; exits 1 when any
        file failed."""
        from mca.capture.batch import (
            BatchError,
            choose_progress,
            open_live_viewer,
            print_summary,
            process_settings,
            report_document,
            run_batch,
            serve_until_interrupted,
        )

        live = None
        try:
            settings = process_settings(
                list(inputs),
                out=out,
                profile=profile,
                workers=workers,
                max_megapixels=max_megapixels,
                quality=quality,
                record=record,
                serve=serve,
                cluster=cluster,
            )
            progress = choose_progress(quiet or as_json, lambda line: typer.echo(line))
            if serve:
                live = open_live_viewer(bind)
                typer.echo(f"rerun viewer: {live.viewer_url}", err=True)
            report = run_batch(
                list(inputs),
                settings.out,
                settings.profile,
                workers=settings.workers,
                cluster=cluster,
                force=force,
                record=record,
                watch=watch,
                watch_timeout_s=watch_timeout,
                poll_interval_s=poll_interval,
                settle_s=settle,
                progress=progress,
                recorder=live,
                max_megapixels=settings.max_megapixels,
                quality=settings.quality,
            )
            if as_json:
                typer.echo(json.dumps(report_document(report), indent=2))
            else:
                print_summary(report)
            if report.recording_error:
                typer.echo(f"error: {report.recording_error}", err=True)
            if live is not None and not report.interrupted:
                typer.echo(f"still serving the viewer at {live.viewer_url}; Ctrl-C to stop", err=True)
                serve_until_interrupted()
        except BatchError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        finally:
            if live is not None:
                live.close()
        if report.failed or report.recording_error:
            raise typer.Exit(1)
