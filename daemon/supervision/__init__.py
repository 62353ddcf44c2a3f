"""Device supervision: each device's connect, backoff, health and lock (``supervisor.py``), used
by the command router and the jobs alike."""
