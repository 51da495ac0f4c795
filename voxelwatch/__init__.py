"""voxelwatch: the umbrella command (``voxelwatch``) and the demo.

The one package that may import every other: each subcommand imports what it
needs inside its own handler.
"""
