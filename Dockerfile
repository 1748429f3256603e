# Builds rayd with the Embree peer and runs it on a slim Debian.
FROM rust:1-bookworm AS build
RUN apt-get update && apt-get install -y --no-install-recommends libembree-dev && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY tests ./tests
COPY scenes ./scenes
RUN cargo build --release --features embree

FROM debian:bookworm-slim
RUN apt-get update && apt-get install -y --no-install-recommends libembree3-3 && rm -rf /var/lib/apt/lists/*
COPY --from=build /src/target/release/rayd /usr/local/bin/rayd
COPY scenes /usr/share/rayd/scenes
WORKDIR /data
# Until the service lands, the default run renders a sample scene into /data.
ENTRYPOINT ["rayd"]
CMD ["render", "/usr/share/rayd/scenes/Fox.glb", "-o", "/data/fox.png"]
