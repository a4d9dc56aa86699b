"""The kinds of cross-validation folds (:mod:`torchcal.data.folds`), by name: importable without
the numerical stack, for the configuration to check against."""

SPLITS = ("grouped", "blocks", "random")
