"""Judging a run: error metrics against ground truth (`metrics`), the crispness of a raw map with no ground truth
(`crispness`) and which poses are crisper and how sure that is (`judge`), the per-scan report (`report`), and the
run's answer (`answer`). Nothing here writes files but the report's CSV (writing/ does)."""
