"""``RUN_DIR/report.html``: a run's results as one self-contained page (``page.py``), from the
run directory's artifacts only (``run_data.py``)."""
