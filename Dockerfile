# One image for the service and the agents: the same commands as on a workstation.
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY encoder_core encoder_core
COPY fleet_wire fleet_wire
COPY encoder_fleet encoder_fleet
COPY edge_agent edge_agent
COPY service service
COPY schemas schemas
COPY migrations migrations
# a real install (not -e): the schemas and migrations must travel as package data; postgres: the scale profile's
# members run on PostgreSQL (psycopg)
RUN pip install --no-cache-dir '.[service,postgres]'
ENTRYPOINT ["encoder-fleet"]
