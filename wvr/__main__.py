import sys

from wvr.cli import main

sys.exit(main())
