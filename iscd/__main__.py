import sys

from iscd.cli import main

sys.exit(main())
