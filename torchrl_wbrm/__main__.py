"""``python -m torchrl_wbrm [overrides]``: the two-stage offline recipe (the ``wbrm-offline`` command)."""
from torchrl_wbrm.cli import wbrm_offline

if __name__ == "__main__":
    wbrm_offline()
