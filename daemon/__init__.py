"""The long-running cell service: owns device links, serves commands, publishes measurements."""
