"""Experiments above the trainers: suites (recipes x envs x seeds), their reports, curriculum chains."""
