"""The daemon's jobs (``cmd/job/<kind>``): the runner, and one module per job kind."""
