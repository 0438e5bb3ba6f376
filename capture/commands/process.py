"""`mca process`: photographs in, depth maps, regions, layers and 3D scenes out (locally, in parallel or on Dask)."""

from __future__ import annotations

import json
from pathlib import Path

import typer


def resolve_profile(name: str | None):
    """The profile for `--profile`: a built-in name or TOML path; `none` is the default filter geometry without lens
    data (results in disparity pixels only)."""
    import dataclasses

    from mca.devices.profiles import DEFAULT_PROFILE, load_profile

    if name is not None and name.lower() == "none":
        base = load_profile(DEFAULT_PROFILE)
        return dataclasses.replace(base, name="none", lens=None, source=f"{base.source} (filter geometry only)")
    return load_profile(name or DEFAULT_PROFILE)


def report_document(report) -> dict:
    """`mca process --json`: every file's outcome, in input order, the totals and the merged recording."""
    from mca.capture.outputs import json_safe

    files = [
        {
            "input": str(o.input_path),
            "status": o.status,
            "output_dir": str(o.output_dir),
            "result": str(o.output_dir / "result.json") if o.status != "failed" else None,
            "seconds": round(o.seconds, 3),
            "regions": o.regions,
            "reason": o.reason,
        }
        for o in sorted(report.outcomes, key=lambda o: str(o.input_path))
    ]
    totals = {status: report.count(status) for status in ("done", "skipped", "failed")}
    return json_safe(
        {
            "files": files,
            "totals": totals,
            "recording": report.recording,
            "recording_error": report.recording_error,
            "interrupted": report.interrupted,
        }
    )


def stop_on_sigterm() -> None:
    """Make SIGTERM (systemctl stop, kill) end this process like Ctrl-C does: through its `finally` blocks."""
    import signal

    def interrupted(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGTERM, interrupted)


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
        import sys

        from mca.capture.batch import BatchError, LineProgress, RichProgress, SilentProgress, print_summary, run_batch
        from mca.capture.config import ConfigError, fill_from_config
        from mca.processing.camera import ProfileError

        try:
            chosen = fill_from_config(profile=profile, workers=workers, output_dir=out)
            profile, workers, out = chosen["profile"], chosen["workers"], chosen["output_dir"]
        except ConfigError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        try:
            camera_profile = resolve_profile(str(profile))
        except ProfileError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        from mca.capture.raw import default_max_megapixels, parse_megapixels

        try:
            max_megapixels = (
                default_max_megapixels()
                if max_megapixels is None
                else parse_megapixels(max_megapixels, "--max-megapixels")
            )
        except ValueError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        from mca.capture.api import check_quality

        try:
            check_quality(quality)
        except ValueError as exc:
            typer.echo(f"error: --quality: {exc}", err=True)
            raise typer.Exit(2) from None
        missing = [str(p) for p in inputs if not p.exists() and not p.is_symlink()]
        if missing:
            typer.echo(f"error: no such file or folder: {', '.join(missing)}; check the path", err=True)
            raise typer.Exit(2)
        if out.exists() and not out.is_dir():
            typer.echo(f"error: --out {out} is a file; give a folder for the outputs", err=True)
            raise typer.Exit(2)
        if record is not None and record.suffix != ".rrd":
            typer.echo(f"error: --record {record}: give a .rrd file name", err=True)
            raise typer.Exit(2)
        progress: SilentProgress | RichProgress | LineProgress
        if quiet or as_json:
            progress = SilentProgress()
        elif sys.stdout.isatty():
            progress = RichProgress()
        else:
            progress = LineProgress(lambda line: typer.echo(line))
        live = None
        if serve:
            if workers > 1 or cluster:
                typer.echo(
                    "error: --serve streams from this process, one file at a time: drop --workers/--cluster, "
                    "or use --record and open the file with `mca view` afterwards",
                    err=True,
                )
                raise typer.Exit(2)
            from mca.capture.recording import RerunRecorder

            stop_on_sigterm()  # a service stop must reach the `finally` below, or the viewer server is orphaned
            try:
                live = RerunRecorder(None, serve=True, bind=bind)
            except RuntimeError as exc:
                typer.echo(f"error: {exc}", err=True)
                raise typer.Exit(2) from None
            typer.echo(f"rerun viewer: {live.viewer_url}", err=True)
        try:
            try:
                report = run_batch(
                    list(inputs),
                    out,
                    camera_profile,
                    workers=workers,
                    cluster=cluster,
                    force=force,
                    record=record,
                    watch=watch,
                    watch_timeout_s=watch_timeout,
                    poll_interval_s=poll_interval,
                    settle_s=settle,
                    progress=progress,
                    recorder=live,
                    max_megapixels=max_megapixels,
                    quality=quality,
                )
            except BatchError as exc:
                typer.echo(f"error: {exc}", err=True)
                raise typer.Exit(2) from None
            if as_json:
                typer.echo(json.dumps(report_document(report), indent=2))
            else:
                print_summary(report)
            if report.recording_error:
                typer.echo(f"error: {report.recording_error}", err=True)
            if live is not None and not report.interrupted:
                import time

                typer.echo(f"still serving the viewer at {live.viewer_url}; Ctrl-C to stop", err=True)
                try:
                    while True:
                        time.sleep(1.0)
                except KeyboardInterrupt:
                    pass
        finally:
            if live is not None:
                live.close()
        if report.failed or report.recording_error:
            raise typer.Exit(1)
