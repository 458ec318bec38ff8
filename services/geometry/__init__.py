"""Pure numpy geometry: rotations, rigid transforms, cameras. No I/O."""
