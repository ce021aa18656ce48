"""Layer 0, the bottom: errors (exit codes), atomic file writes, progress reporting. Imports nothing of pipeline."""
