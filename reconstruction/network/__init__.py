"""The acquisition network (paper §6): its architecture, training data, training and the shipped networks."""
