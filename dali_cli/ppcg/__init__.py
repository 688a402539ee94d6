"""Pseudo point cloud generation (PPCG): model selection and fitting, angular windows, RC and CF.

`fitting` picks a library model for each pseudo box and places it (anisotropic scale, pose);
`window` finds the sensor rays that can see a box; `point_models` ray-casts point models with an
angular index; `rc` and `cf` turn one frame's points and boxes into its pseudo point cloud.
"""
