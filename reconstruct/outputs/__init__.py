"""What a solve writes: `points3d.csv` and `sequencing.json` (`points`), the rerun recording (`recording`), and the
CSV/TRC/C3D exports (`export`, with the motion-capture file formats in `mocap`)."""
