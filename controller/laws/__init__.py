"""The control laws.

Feed and uniformity loops, QP, limits, identification, knife phase, offset history, design
checks (pure: no asyncio, threads or buses).
"""
