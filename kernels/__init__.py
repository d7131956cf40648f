"""NVIDIA Warp kernels, one module per stage (installed as `warpbags.kernels`).

Nothing here imports torch: the torch side lives in `warpbags/`.
"""
