"""Scoring against the truth: ``metrics`` (projection difference, parameter and pose errors,
where an estimate is valid) and ``stage`` (the per-camera stage every run shares: detect,
calibrate with each method, score when there is a truth).
"""
