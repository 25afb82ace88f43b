"""Policies and fine-tuning on top of envs. Nothing here yet."""
