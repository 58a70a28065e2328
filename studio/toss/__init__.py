"""The ball toss: toss primitives, lift detection, recordings and the toss model used by evaluation."""
