"""Machinery shared by the tests: what every test is checked against, and ways to wait."""
