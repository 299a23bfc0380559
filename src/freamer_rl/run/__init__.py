"""Run infrastructure every trainer shares: run directory (lock, resume, SIGTERM), checkpoints, collectors, envs
from the adapter registry, episode statistics, progress files and curves, the optimiser step, the collect-learn loop.
Imports no trainer and no model: a trainer hands it factories and hooks."""
