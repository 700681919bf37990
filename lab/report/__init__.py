"""Report writing: markdown tables and the command and machine behind each result page, and the figures."""
