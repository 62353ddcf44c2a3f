"""Algorithms and bus workers: scanner decoding, calibration, fusion, metrics.

Never imports scancell.daemon.
"""
