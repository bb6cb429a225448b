"""2D point tracks through every video. Owns the `tracks.csv` contract (`tracking.tracks`)."""
