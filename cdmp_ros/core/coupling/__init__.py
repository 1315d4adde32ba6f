"""Obstacle coupling of CDMPs (paper 000, Eq. 7 and 12): potential fields, closest points and
the joint-space terms."""
