"""Benchmarks behind `dvla bench ...`; each saves JSON and reports figures measured in one run."""
