"""Reconstruction methods (UltrON, its ablation, baselines) behind one registry."""
