"""`python -m dvla ...` is the `dvla` command."""

from dvla.orchestrator.cli import main

main()
