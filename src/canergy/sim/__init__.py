"""The paper's case study and beyond: discrete-event simulation of strategies over channels."""
