"""Training: the config, the spool-backed data, the losses, the loop and what it reports."""
