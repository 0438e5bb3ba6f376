"""The viewer layout of a recording: input | regions | depth, then the 3D scene, the order and the timings."""

from __future__ import annotations

from typing import Any


def default_blueprint() -> Any:
    """The layout a newcomer sees: input | regions | depth, then the 3D scene, the order and the timings."""
    import rerun.blueprint as rrb

    top = rrb.Horizontal(
        rrb.Spatial2DView(origin="shot/input", name="Input (as the camera produced it)"),
        rrb.Spatial2DView(origin="shot", contents=["+ $origin/all_in_focus", "+ $origin/segmentation"], name="Regions"),
        rrb.Spatial2DView(origin="shot/depth", name="Depth (mm)"),
    )
    middle = rrb.Horizontal(
        rrb.Spatial3DView(origin="world", name="3D scene (m)"),
        rrb.Tabs(
            rrb.TextDocumentView(origin="shot/occlusion_order", name="Occlusion order"),
            rrb.GraphView(origin="shot/occlusion_graph", name="Occlusion graph"),
            rrb.TextDocumentView(origin="shot/summary", name="Summary"),
            rrb.TextDocumentView(origin="shot/profile", name="Profile"),
            rrb.TextDocumentView(origin="shot/input_metadata", name="Input file"),
        ),
        rrb.TimeSeriesView(origin="timings", name="Timings (s)"),
        column_shares=[2, 1.3, 1],
    )
    bottom = rrb.Tabs(
        rrb.Grid(
            rrb.Spatial2DView(origin="shot/raw/red", name="Raw red"),
            rrb.Spatial2DView(origin="shot/raw/green", name="Raw green"),
            rrb.Spatial2DView(origin="shot/raw/blue", name="Raw blue"),
            name="Raw planes",
        ),
        rrb.Horizontal(
            rrb.Spatial2DView(origin="shot/channels/before", name="Misalignment before"),
            rrb.Spatial2DView(origin="shot/channels/after", name="After re-alignment"),
            name="Channels",
        ),
        rrb.Horizontal(
            rrb.Spatial2DView(origin="shot/disparity/region_model", name="Disparity, region model (px)"),
            rrb.Spatial2DView(origin="shot/disparity/per_pixel", name="Disparity, per pixel (px)"),
            rrb.Spatial2DView(origin="shot/disparity/confidence", name="Confidence"),
            name="Disparity",
        ),
        rrb.Spatial2DView(origin="shot/multi_plane", name="Multi-plane images (toggle layers)"),
        rrb.Spatial2DView(origin="shot/stages", name="Stages"),
    )
    return rrb.Blueprint(rrb.Vertical(top, middle, bottom, row_shares=[3, 3, 2]), collapse_panels=False)
