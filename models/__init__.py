"""The shipped delay-model bundles (data only; see README.md beside this file)."""
