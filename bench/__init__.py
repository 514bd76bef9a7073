"""Benchmark scripts (run each as ``python bench/NAME.py``) and their shared helpers."""
