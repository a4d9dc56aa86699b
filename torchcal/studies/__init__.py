"""Optuna studies over torchcal configurations (``torchcal study``).

:mod:`spec` declares a study (search space, objectives, storage), :mod:`storage` opens SQLite or
any RDB URL with heartbeats so that a killed trial is failed and retried, :mod:`objective` scores
one trial, :mod:`runner` runs workers and refits the best trial, :mod:`report` writes the report.
"""
