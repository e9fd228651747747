"""One module per `dvla` command."""
