"""``python -m vkray``: ``info`` (devices, backends, limits, what to install) and ``bench`` (see vkray._cli)."""

import sys

from ._cli import main

if __name__ == "__main__":
    sys.exit(main())
