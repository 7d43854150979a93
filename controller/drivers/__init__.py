"""Elastoprobe controller.drivers."""
