"""Trainers: one module per entry of :data:`freamer_rl.trainers.registry.TRAINERS`, named as its key
(``minigrid_ppo``, ``health``; the TorchRL baselines ``ppo_baseline``, ``impala``, ``dreamer_v3`` under
:mod:`.baselines`)."""
