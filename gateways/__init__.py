"""Gateways from the cell's bus to the protocols plants speak (OPC UA)."""
