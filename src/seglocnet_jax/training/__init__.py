"""Training machinery: optimizer and state, the sharded step, checkpoints, logging, the loop."""
