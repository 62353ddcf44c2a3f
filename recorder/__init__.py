"""MCAP recording, replay and offline reprocessing of cell sessions."""
