"""Test suites that implementations of torchcal's extension points import and run."""
