"""The operator console in a browser (``iorthand web``): a phone or a desktop drives the robot through the edge's
safety core like any other operator client."""
