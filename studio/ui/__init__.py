"""The viser studio and the Panel dashboard (thin front ends over the core)."""
