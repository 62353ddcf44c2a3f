"""Bus workers: each subscribes to the cell's keys, runs algorithms from ``analysis/`` on a thread
of its own (:class:`scancell.workers.base.ThreadedWorker`) and publishes the results.

scan, calibrate, fuse, the live Foxglove bridge (monitor), and offline reprocessing of a recording
(which drives the same workers on an in-process bus).
"""
