"""``python -m sb3_spikeplastic``: the ``sb3-spikeplastic`` command line (:mod:`sb3_spikeplastic.cli`)."""

import sys

from sb3_spikeplastic.cli import main

sys.exit(main())
