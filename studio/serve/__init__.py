"""Serves: parameters and files, the evaluation chain (plan, ball, ITTF checks, reward) and the joint-effort check."""
