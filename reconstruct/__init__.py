"""Sync-free 3D reconstruction: the self-expressive solver of Zheng et al. (PAMI / ICCV 2015).

Owns `points3d.csv` and `sequencing.json` (`reconstruct.outputs.points`).
"""
