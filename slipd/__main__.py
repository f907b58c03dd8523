import sys

from slipd.cli import main

sys.exit(main())
