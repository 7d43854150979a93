"""Elastoprobe sim.servers."""
