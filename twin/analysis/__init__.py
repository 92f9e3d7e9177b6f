"""Model-vs-measurement analysis: load campaigns, predict them, compare, diagnose, improve."""
