import sys

from massviz.cli import main

sys.exit(main())
