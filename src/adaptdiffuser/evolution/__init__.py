"""Self-evolution building blocks: synthetic tasks, generation, and the rule-based discriminator."""
