"""Designs of experiments: definitive screening designs (``dsd``)."""
