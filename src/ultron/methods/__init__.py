"""Reconstruction methods (UltrON, its ablation, baselines) and the shared run outputs."""
