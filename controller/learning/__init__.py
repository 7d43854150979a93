"""Elastoprobe controller.learning."""
