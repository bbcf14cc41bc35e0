"""The CUDA device: the same scene, BVH, shading and audit as the CPU, on numba's CUDA target.

Nothing here is imported unless ``device = "cuda"`` is asked for; ``engine.gpu.device`` says
in one line what is missing when it cannot be.
"""
