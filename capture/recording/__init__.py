"""Rerun recordings of the pipeline: every stage of a shot logged to an .rrd file (or a local web viewer), and merged.

`RerunRecorder` implements the `processing.result.Recorder` protocol and adds the
application's own calls around a run of the pipeline::

    recorder = RerunRecorder(Path("out/c.rrd"))
    recorder.begin_shot(0, "paper-c", capture_time, profile)
    recorder.log_input(frame)                      # raw colour planes, the input as the camera produced it
    result = run_pipeline(..., recorder=recorder)  # stages call record() and timing()
    recorder.log_result(result, profile, optics)   # regions, order, depth, multi-plane images, 3D scene
    recorder.close()

Entity paths (all per shot, on the `shot` sequence timeline and the `capture_time` timeline):

    shot/input                   EncodedImage   the input image as the camera produced it (display size, JPEG)
    shot/raw/{red,green,blue}    EncodedImage   the raw colour planes (grey JPEG)
    shot/channels/before         EncodedImage   red plane in red, blue plane in cyan: the MCA misalignment
    shot/channels/after          EncodedImage   the same after re-alignment (the all-in-focus image)
    shot/disparity/region_model  Image (F32)    disparity of the region model, input px, + = farther
    shot/disparity/per_pixel     Image (F32)    per-pixel disparity estimate, input px
    shot/disparity/confidence    Image (F32)    confidence in [0, 1]
    shot/segmentation            SegmentationImage + AnnotationContext (region id -> "#id 1234 mm")
    shot/occlusion_order         TextDocument   markdown table, front to back
    shot/occlusion_graph         GraphNodes + GraphEdges (an edge a -> b: a occludes b)
    shot/depth                   DepthImage     distance from the lens in mm (meter=1000), 0 = unknown
    shot/all_in_focus            EncodedImage   fringes removed
    shot/multi_plane/NN          Image (RGBA) + Transform3D  the multi-plane images, nearest first, each
                                 cropped to where it is opaque and translated to its place
    shot/profile                 TextDocument   the camera profile used
    shot/summary                 TextDocument   shot name, time, timings
    shot/segmentation/sketch     SegmentationImage  the 2.1D sketch's regions on the analysis grid
    shot/stages/<stage>/<item>   Image/Scalars/TextDocument  anything else a stage reported through record()
    world                        ViewCoordinates RUB (static): the scene frame of scene.ply and scene.glb,
                                 metres, x right, y up, the camera at the origin looking down -z (glTF)
    world/camera                 Pinhole        f = d_ls / pitch px, principal point at the centre, camera_xyz RUB
    world/camera/image           EncodedImage   the input, seen through the pinhole
    world/points                 Points3D       coloured point cloud: scene.ply's points (subsampled)
    world/planes/NN              Mesh3D         the accurate-depth planes, coloured, on their (slanted) surfaces

    timings/<stage>              Scalars        seconds per stage

The colours of every displayed image are the camera's (`capture.raw.RawFrame.colour`: as-shot white
balance and colour matrix); the 3D coordinates come from the one camera model, `processing.pinhole`.

One job a module:

    rerun_env   rerun's command-line binary, and its usage analytics kept off (`disable_rerun_analytics`)
    display     what the viewer shows: images at display size in sRGB, markdown tables, multi-plane crops
    scene       the 3D scene: accurate-depth plane meshes through the one camera model (`processing.pinhole`)
    recorder    `RerunRecorder`, the `processing.result.Recorder` of the application
    serve       the local web viewer (`--serve`): ports, its process, stopping it
    blueprint   the viewer layout
    merge       several recordings merged into one

The names below are the package's public face; nothing here is imported by `processing`, and rerun
itself is imported only when a recorder is made.
"""

from __future__ import annotations

from mca.capture.recording.blueprint import default_blueprint
from mca.capture.recording.display import DISPLAY_MEGAPIXELS, display_size, to_srgb8
from mca.capture.recording.merge import merge_recordings
from mca.capture.recording.recorder import RecordingWriteError, RerunRecorder
from mca.capture.recording.rerun_env import (
    child_environment,
    disable_rerun_analytics,
    quiet_rerun_environment,
    rerun_analytics_config_path,
    rerun_analytics_disabled,
    rerun_executable,
)
from mca.capture.recording.scene import plane_mesh
from mca.capture.recording.serve import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT, choose_port

__all__ = [
    "DEFAULT_GRPC_PORT",
    "DEFAULT_WEB_PORT",
    "DISPLAY_MEGAPIXELS",
    "RecordingWriteError",
    "RerunRecorder",
    "child_environment",
    "choose_port",
    "default_blueprint",
    "disable_rerun_analytics",
    "display_size",
    "merge_recordings",
    "plane_mesh",
    "quiet_rerun_environment",
    "rerun_analytics_config_path",
    "rerun_analytics_disabled",
    "rerun_executable",
    "to_srgb8",
]
