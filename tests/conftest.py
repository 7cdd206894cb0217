"""Test-suite set-up: pytest's default (prepend) import mode puts this folder on ``sys.path`` when it loads this file,
which makes the shared helpers (``_compose``) importable from every test module, sub-folders included."""
