"""The views wing: depth colour maps and figures, and the 3D reconstruction (point clouds, meshes, PLY).
"""
