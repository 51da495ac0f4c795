"""Calibrating cameras from a printed chessboard (``voxelwatch calibrate``).

* :mod:`.board`: the board, finding it in an image, naming its corners alike in every camera;
* :mod:`.clips`: reading clips, cutting floor clips into still stretches;
* :mod:`.intrinsics`: a lens from a board moved in front of the camera;
* :mod:`.floor`: every camera's pose from a board laid on the floor (chaining, bundle adjustment,
  placement in the room);
* :mod:`.write`: writing the site's calibration files, all or none, with backups;
* :mod:`.command`: the command line.

The boards of the synthetic worlds that check all this against true cameras are drawn by
:mod:`common.synth.board`.
"""
