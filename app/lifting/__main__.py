import sys

from app.lifting.worker import main

sys.exit(main(sys.argv[1:]))
