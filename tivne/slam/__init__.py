"""Online SLAM: tracking, mapping, keyframes, the per-frame loop (system), checkpoints and run outputs."""
