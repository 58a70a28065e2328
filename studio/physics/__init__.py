"""Ball physics: flight (drag, Magnus), table, net and racket impacts, the court, and their fits on measured data."""
