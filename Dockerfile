# rayd serve on a slim Debian, with the Embree peer. Build: docker build -t rayd .
# Run: docker run -p 8080:8080 -v rayd-data:/data rayd
# (a named volume; a host directory bind-mounted at /data must be writable by uid 10001)
FROM rust:1-bookworm AS build
RUN apt-get update \
 && apt-get install -y --no-install-recommends libembree-dev \
 && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY proto ./proto
COPY scenes ./scenes
RUN cargo build --release --features embree --bin rayd

FROM debian:bookworm-slim
RUN apt-get update \
 && apt-get install -y --no-install-recommends libembree3-3 \
 && rm -rf /var/lib/apt/lists/* \
 && groupadd --system --gid 10001 rayd \
 && useradd --system --uid 10001 --gid rayd --home-dir /data --shell /usr/sbin/nologin rayd \
 && mkdir -p /data \
 && chown rayd:rayd /data
COPY --from=build /src/target/release/rayd /usr/local/bin/rayd
# The store for every command run in the container (`docker exec … rayd backup --out
# /data/backup-1` copies the live store).
ENV RAYD_DATA_DIR=/data
USER rayd
WORKDIR /data
VOLUME /data
EXPOSE 8080
# SIGTERM starts the graceful shutdown (--grace seconds, default 5); give `docker stop`
# more than that (its default of 10 s does).
STOPSIGNAL SIGTERM
# Docker's timeout above `rayd healthcheck`'s own 3 s, so that its message is the one logged.
HEALTHCHECK --interval=10s --timeout=5s --start-period=10s --retries=3 \
  CMD ["rayd", "healthcheck"]
ENTRYPOINT ["rayd"]
# Flags win over RAYD_* variables: to change one, give the command whole, for example
# `docker run … rayd serve --addr 0.0.0.0:8080 --data-dir /data --threads 8`.
CMD ["serve", "--addr", "0.0.0.0:8080", "--data-dir", "/data"]
