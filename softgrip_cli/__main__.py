"""``python -m softgrip_cli``: the ``softgrip`` command."""

import sys

from softgrip_cli._main import main

sys.exit(main())
