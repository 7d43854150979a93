"""Elastoprobe calibration."""
