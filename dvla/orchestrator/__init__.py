"""Orchestration: topology files, process placement and the `dvla` command line."""
