"""The console's library logging, set when ``torchrl_wbrm`` is imported: quiet unless asked.

torchrl logs an ``[INFO]`` line for every storage it initialises (and minari, h5py and tensordict have their own
INFO chatter); none of it is the user's business by default. :func:`quiet_libraries` raises those loggers to
WARNING (after importing torchrl, which sets its logger's level when first imported); the environment is left as it
is. A user who sets ``RL_LOGGING_LEVEL`` or ``TORCHRL_WBRM_VERBOSE=1`` keeps the libraries' INFO lines; the recipes'
``verbose=true`` brings them back too (``torchrl_wbrm.training.logging.configure_console``).
"""
from __future__ import annotations

import logging
import os

__all__ = ["CHATTY_LOGGERS", "quiet_libraries", "route_mujoco_warnings"]

#: Loggers whose INFO lines (storage initialisation and the like) are silenced unless asked for.
CHATTY_LOGGERS = ("torchrl", "tensordict", "minari", "h5py")


def quiet_libraries(verbose: bool | None = None) -> None:
    """Silence the libraries' INFO logging (``verbose=False``) or bring it back (``True``); ``None``: quiet unless
    ``TORCHRL_WBRM_VERBOSE`` is set (to anything but ``0``) or ``RL_LOGGING_LEVEL`` was chosen by the user."""
    if verbose is None:
        if os.environ.get("TORCHRL_WBRM_VERBOSE", "0") not in ("", "0") or "RL_LOGGING_LEVEL" in os.environ:
            return
        verbose = False
    import torchrl  # noqa: F401  (it configures its logger when first imported: set the level after that)

    level = logging.INFO if verbose else logging.WARNING
    for name in CHATTY_LOGGERS:
        logger = logging.getLogger(name)
        logger.setLevel(level)
        for handler in logger.handlers:  # torchrl's own console handler takes RL_LOGGING_LEVEL too
            handler.setLevel(level)


def _mujoco_warning(message: str) -> None:
    import warnings

    warnings.warn(f"MuJoCo: {' '.join(message.split())}", RuntimeWarning, stacklevel=2)


def route_mujoco_warnings() -> None:
    """MuJoCo's warnings as Python ``RuntimeWarning``s (``mujoco.set_mju_user_warning``), where MuJoCo is installed
    and no handler is set yet. Its default handler prints each warning on stdout and appends it to
    ``MUJOCO_LOG.TXT`` in the working directory, a file outside any folder a command was given (``HalfCheetah-v5``'s
    model warns at every ``gymnasium.make``, so a run's evaluations wrote hundreds of lines there). Python's warning
    filters then show each message once per place."""
    try:
        import mujoco
    except ImportError:
        return
    if mujoco.get_mju_user_warning() is None:
        mujoco.set_mju_user_warning(_mujoco_warning)
