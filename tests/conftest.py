"""Puts the shared helpers in reach: pytest's default ("prepend") import mode inserts the folder
of this file, tests/, on sys.path, so every test folder can ``import loopback``."""
