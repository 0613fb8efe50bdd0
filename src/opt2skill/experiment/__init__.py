"""Experiments of the paper as resumable commands (`opt2skill experiment ...`, docs/experiments.md)."""
