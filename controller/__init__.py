"""Elastoprobe controller."""
