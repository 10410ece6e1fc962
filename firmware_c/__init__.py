"""The agent firmware in C (README.md here): its sources travel with the Python
packages as package data, so that ``pip install .`` builds the C agent, its library and
its node program anywhere (sim.cbind.cimpl builds them with this directory's Makefile into a
cache), not only in a checkout. There is no Python API here."""
