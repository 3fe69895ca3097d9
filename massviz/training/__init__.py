"""Training the mass CNN with the paper's protocol: patch extraction (``extract``) and training (``train``)."""
