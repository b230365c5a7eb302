"""shadecap.capture — from photos to maps.

Datasets, synthetic capture, observations, solvers, reconstruction, metrics, the command line.
"""
