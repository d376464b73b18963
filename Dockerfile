# One image for the service and the agents: the same commands as on a workstation.
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY encoder_core encoder_core
COPY encoder_fleet encoder_fleet
COPY edge_agent edge_agent
COPY service service
COPY schemas schemas
COPY migrations migrations
RUN pip install --no-cache-dir -e .
ENTRYPOINT ["encoder-fleet"]
