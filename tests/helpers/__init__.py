"""Helpers shared by several test modules (imported as `tests.helpers.NAME`; the tests are a package, so no test
edits sys.path): in-memory recordings for the driver tests and independent AEDAT4 readers used as oracles."""
