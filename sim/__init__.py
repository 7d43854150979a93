"""Elastoprobe sim."""
