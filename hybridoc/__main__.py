"""``python -m hybridoc``: the same as the ``hybridoc`` command."""

from hybridoc.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
