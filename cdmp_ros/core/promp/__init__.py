"""ProMPs (paper 003, Section II-A): the distribution, its primitive file, Gaussian helpers and
accurate tails."""
