"""File and bag I/O. Every writer goes through ``atomic`` so no half-written output remains."""
