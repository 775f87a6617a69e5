import sys

from iscd.cli.main import main

sys.exit(main())
