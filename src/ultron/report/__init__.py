"""Reporting: tables (and, later, figures and the HTML report)."""
