"""HEBO optimization of serves, robustification on recorded tosses, training many serves."""
