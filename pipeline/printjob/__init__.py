"""Print jobs: G-code and model references, deviation, verdicts and the job store."""
