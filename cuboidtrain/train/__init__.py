"""Training: the config, the spool-backed data, the losses, the loop, checkpoints' housekeeping and evaluation."""
