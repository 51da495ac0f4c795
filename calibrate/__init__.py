"""Calibrating cameras from a printed board (``voxelwatch calibrate``).

* :mod:`.board`: the chessboard, finding it in an image, naming its corners alike in every camera;
* :mod:`.charuco`: the ChArUco board (markers name its corners), for lenses from partial views;
* :mod:`.clips`: reading clips, cutting floor clips into still stretches;
* :mod:`.intrinsics`: a lens from a board moved in front of the camera;
* :mod:`.floor`: every camera's pose from a board laid on the floor (chaining, bundle adjustment,
  placement in the room);
* :mod:`.write`: writing the site's calibration files, all or none, with backups;
* :mod:`.command`: the command line.

The boards of the synthetic worlds that check all this against true cameras are drawn by
:mod:`synth.board`.
"""
