"""`python -m stack run` starts the whole stack (what `make run` execs); see stack/run.py."""

import sys

from stack.run import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
