"""The simulated cell: a physically faithful digital twin with ground truth.

Only simulator servers, tests and benchmarks import this package; real drivers never do.
"""
