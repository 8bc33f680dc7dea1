"""`python -m gateway` = `hil-gateway`."""

import sys

from gateway.cli import main

sys.exit(main())
