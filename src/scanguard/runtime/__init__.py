"""Executors: run independent tasks locally or on a Ray cluster (the bottom layer)."""
