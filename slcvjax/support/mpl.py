"""matplotlib for the package's figures, without taking the caller's backend."""

import sys


def pyplot():
    """``matplotlib.pyplot``, with the headless Agg backend unless the caller already uses pyplot
    (a notebook's inline backend, a desktop window), whose choice is kept."""
    import matplotlib

    if "matplotlib.pyplot" not in sys.modules:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
