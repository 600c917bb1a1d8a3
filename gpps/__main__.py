import sys

from gpps.cli import main

sys.exit(main())
