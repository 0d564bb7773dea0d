"""The light path: the scene and the eye, the differentiable model of the plate (and its fused
CPU kernels), diffraction, the baselines it is judged against and the ray trace of a written mesh.
"""
