"""Embedded synthetic localisation benchmark: textured rooms seen by moving pinhole cameras.

The package is split at its seams: ``camera`` (pinhole model, pose conventions), ``scene``
(rooms, boxes, textures, camera routes), ``raycast`` (the renderer and the camera response),
``trajectories`` (train and test sequences), ``nuisances`` (optional lighting change,
occluders, sensor noise and motion blur), ``surfaces`` (optional plain, repeated and glossy
surfaces), ``capture`` (an optional camera pipeline, JPEG and larger images) and ``writer``
(datasets on disk); every public name is importable from here.

Each scene is a room (an axis-aligned box seen from inside, a few metres wide like the
7-Scenes rooms) holding a few axis-aligned boxes and thin panels. Every face carries its own
procedural texture: large coloured gradients and shapes (so a 64 px view tells where the
camera is and where it looks) plus finer detail. Images are ray cast exactly in numpy,
with a point light and 2×2 supersampling, then pass through a per-sequence camera response
(gain, bias, tint, gamma, sensor noise). The pose can only be learnt from what the camera sees.
Nuisances, all off by default (:class:`Nuisances`), add what no scene model explains: lighting
and exposure changing between and within sequences, person-sized occluders in front of the
camera, more sensor noise and motion blur. Surfaces and capture of real data, all off by
default too (:class:`SurfaceOptions`, :class:`CaptureOptions`), take away what makes the
plain benchmark kind to render-and-compare: texture-poor, periodic and glossy surfaces,
vignetting, gamma, drifting auto-exposure and white balance, JPEG, images larger than the
compare width.

Conventions:

- World frame: metres, ``z`` up, floor at ``z = 0``, room centred on ``x = y = 0``.
- Poses ``[7]`` = ``x, y, z, qw, qx, qy, qz``, camera-to-world, ``qw >= 0``.
- Camera frame (OpenCV): ``x`` right, ``y`` down, looking along ``+z``.
- Pixels: the centre of pixel ``(u, v)`` (column, row) lies at integer coordinates ``(u, v)``;
  the principal point is the image centre ``((W - 1) / 2, (H - 1) / 2)`` and
  ``fx = fy = (W / 2) / tan(fov / 2)`` for the horizontal field of view ``fov``.
- Textures: texel ``(row i, column j)`` of a face covers face coordinates
  ``a ∈ [j·s, (j+1)·s)``, ``b ∈ [i·s, (i+1)·s)`` (texel size ``s`` metres); its centre is at
  ``((j + 0.5)·s, (i + 0.5)·s)``. Textures are sampled bilinearly between texel centres.

Layout written by :func:`write_synthetic_dataset` (label format of :mod:`pae.data.labels`)::

    OUT/labels/scene00_train.csv  OUT/labels/scene00_test.csv  ...  OUT/labels/all_{train,test}.csv
    OUT/scene00/seq-01/frame-000000.png  ...
    OUT/labels/nuisances.csv   (only with a nuisance or the camera pipeline on: img_path,
                                occluder_share, blur_px, exposure_gain per frame)
"""

from pae.synthetic.camera import (
    DEFAULT_FOV_DEG,
    DEFAULT_SIZE,
    PinholeCamera,
    pose_rotation_translation,
    world_to_camera,
)
from pae.synthetic.capture import (
    JPEG_QUALITY_RANGE,
    RENDER_SCALE_MAX,
    CaptureOptions,
    sequence_capture,
)
from pae.synthetic.nuisances import (
    MOTION_DEPTH_M,
    NUISANCE_BOUNDS,
    OCCLUDER_DISTANCE_M,
    OCCLUDER_SIZE_M,
    Nuisances,
    person_textures,
    sequence_nuisances,
)
from pae.synthetic.raycast import (
    AUTO_EXPOSURE_RANGE,
    AUTO_EXPOSURE_TARGET,
    RAYS_PER_CHUNK,
    SUPERSAMPLE,
    Appearance,
    FrameConditions,
    jpeg_roundtrip,
    motion_kernel,
    render,
    render_batch,
    shade_rays,
    vignette,
)
from pae.synthetic.scene import (
    DEFAULT_TEST_OFFSET_M,
    DEFAULT_TRAIN_LANE_M,
    TEXEL_SIZE_M,
    Box,
    CameraRoute,
    FaceTexture,
    SyntheticScene,
    furnish,
    make_scene,
    room_textures,
    scene_name,
)
from pae.synthetic.surfaces import (
    REPEAT_PERIOD_M,
    SURFACE_BOUNDS,
    SurfaceOptions,
    dress_surfaces,
)
from pae.synthetic.trajectories import (
    DEFAULT_STRAY_M,
    DEFAULT_YAW_STRAY_RAD,
    TEST_SEQUENCES,
    TRAIN_SEQUENCES,
    CameraSequence,
    make_sequences,
)
from pae.synthetic.writer import (
    DEFAULT_SCENES,
    DEFAULT_TEST_FRAMES,
    DEFAULT_TRAIN_FRAMES,
    FRAMES_PER_WRITE,
    NUISANCE_COLUMNS,
    NUISANCE_FILE,
    RenderProgress,
    SyntheticSummary,
    render_frames,
    scaled_blur,
    sequence_conditions,
    surface_seed,
    write_label_files,
    write_nuisance_table,
    write_synthetic_dataset,
    write_whole,
)

__all__ = [
    "AUTO_EXPOSURE_RANGE",
    "AUTO_EXPOSURE_TARGET",
    "DEFAULT_FOV_DEG",
    "DEFAULT_SCENES",
    "DEFAULT_SIZE",
    "DEFAULT_STRAY_M",
    "DEFAULT_TEST_FRAMES",
    "DEFAULT_TEST_OFFSET_M",
    "DEFAULT_TRAIN_FRAMES",
    "DEFAULT_TRAIN_LANE_M",
    "DEFAULT_YAW_STRAY_RAD",
    "FRAMES_PER_WRITE",
    "JPEG_QUALITY_RANGE",
    "MOTION_DEPTH_M",
    "NUISANCE_BOUNDS",
    "NUISANCE_COLUMNS",
    "NUISANCE_FILE",
    "OCCLUDER_DISTANCE_M",
    "OCCLUDER_SIZE_M",
    "RAYS_PER_CHUNK",
    "RENDER_SCALE_MAX",
    "REPEAT_PERIOD_M",
    "SUPERSAMPLE",
    "SURFACE_BOUNDS",
    "TEST_SEQUENCES",
    "TEXEL_SIZE_M",
    "TRAIN_SEQUENCES",
    "Appearance",
    "Box",
    "CameraRoute",
    "CameraSequence",
    "CaptureOptions",
    "FaceTexture",
    "FrameConditions",
    "Nuisances",
    "PinholeCamera",
    "RenderProgress",
    "SurfaceOptions",
    "SyntheticScene",
    "SyntheticSummary",
    "dress_surfaces",
    "furnish",
    "jpeg_roundtrip",
    "make_scene",
    "make_sequences",
    "motion_kernel",
    "person_textures",
    "pose_rotation_translation",
    "render",
    "render_batch",
    "render_frames",
    "room_textures",
    "scaled_blur",
    "scene_name",
    "sequence_capture",
    "sequence_conditions",
    "sequence_nuisances",
    "shade_rays",
    "surface_seed",
    "vignette",
    "world_to_camera",
    "write_label_files",
    "write_nuisance_table",
    "write_synthetic_dataset",
    "write_whole",
]
