"""The stereo vision service: cameras behind the `Camera` role and the streaming pipeline.

`camera` (the role, `StereoPair`), `backends` (`open_camera(config)`), `sim_camera` +
`render` + `rig` (the simulated rig), `opencv_camera` (devices and files), `pipeline`
(capture → encode → publish, dropping frames), `config` (`VisionConfig`). The render bench
is `services.tools.bench.render`.
"""
