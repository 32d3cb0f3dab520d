"""The paper's method, on the ground floor: the camera convention, the network, the five losses with
the signed distance fields and their nearest-point search, the metrics, and the one error type a
user's mistake raises. Nothing here imports from the rest of the package; the rest builds on it.
"""
