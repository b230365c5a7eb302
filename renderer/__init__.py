"""shadecap.renderer — how light reaches a camera.

Meshes, cameras, G-buffers, lights, shadows, differentiable shading, image I/O.
"""
