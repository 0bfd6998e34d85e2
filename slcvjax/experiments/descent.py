"""The designs' optimiser: Adam-scaled gradient steps, each shortened until it lowers the value.

Both designs (:func:`slcvjax.experiments.design.optimise`, the sensor poses of a calibration, and
:func:`slcvjax.experiments.laser_design.optimise_lasers`, the lasers' mounting) minimise a
predicted error whose gradient is blind to discrete events (a dot leaving the image, a beam
meeting another wall, a constraint broken).  So every Adam step (:func:`optax.scale_by_adam`) is
tried at its full length and shortened by a line search of the design's own (which re-evaluates
the value there, events included) until the value goes down.
"""

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import optax


class Accepted(NamedTuple):
    """A step the line search accepts: the new point, its value and gradient, the step length
    used, and whatever else the design evaluated there (``extra``)."""

    u: Any
    value: Any
    grad: Any
    lr: float
    extra: Any = None


class Descent(NamedTuple):
    """Where :func:`adam_descent` ended: the point, its value and gradient, the value after every
    accepted step (the start first), and the last accepted step's ``extra`` (None if none)."""

    u: Any
    value: Any
    grad: Any
    history: list[float]
    extra: Any


def adam_descent(
    u0,
    value0,
    grad0,
    search: Callable[[Any, Any, float, float], Accepted | None],
    steps: int,
    learning_rate: float,
    adam: optax.GradientTransformation,
    grow: float | None = None,
    restart: bool = False,
    progress: str | None = None,
    postfix: Callable[[float], dict] | None = None,
) -> Descent:
    """Adam-scaled descent from ``u0`` (value ``value0``, gradient ``grad0``).

    Each iteration takes Adam's direction and asks ``search(u, direction, lr, value)`` for a step
    ``u - a * direction`` (``a <= lr``) that lowers ``value``; it stops after ``steps`` accepted
    steps, or where the search finds none.  ``grow``: the next step starts at ``grow`` times the
    length just accepted (at most ``learning_rate``; None: always at ``learning_rate``).
    ``restart``: where the search finds no step, Adam starts afresh once (its moments may carry the
    point against an event's edge) before giving up.  ``progress``: a progress bar's title.
    """
    u, value, grad = u0, value0, grad0
    history = [float(value0)]
    state = adam.init(u)
    lr, restarted, extra = learning_rate, False, None
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=steps, desc=progress, unit="step")
    try:
        while len(history) <= steps:
            with jax.numpy_dtype_promotion("standard"):  # optax mixes an int32 count into float powers
                direction, state = adam.update(grad, state)
            found = search(u, direction, lr, history[-1])
            if found is None:
                if not restart or restarted:
                    break
                state, lr, restarted = adam.init(u), learning_rate, True
                continue
            restarted = False
            u, value, grad, extra = found.u, found.value, found.grad, found.extra
            lr = min(found.lr * grow, learning_rate) if grow is not None else learning_rate
            history.append(float(value))
            if bar is not None:
                bar.update(1)
                if postfix is not None:
                    bar.set_postfix(**postfix(float(value)))
    finally:
        if bar is not None:
            bar.close()
    return Descent(u, value, grad, history, extra)
