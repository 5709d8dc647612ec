"""``python -m softplot``: the same command line as the ``softplot`` script."""

from softplot.cli import main

if __name__ == "__main__":
    main()
