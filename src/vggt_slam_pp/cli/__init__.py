"""Command-line interface (``vggt-slam-pp``)."""
