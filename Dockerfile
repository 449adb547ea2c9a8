FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY terrasift ./terrasift
RUN pip install --no-cache-dir .
# compile the numba kernels into the image (otherwise each worker of the first job does)
RUN python -m terrasift.warmup
ENV TERRASIFT_DATA_DIR=/data
VOLUME ["/data"]
EXPOSE 8000
CMD ["terrasift", "serve", "--host", "0.0.0.0", "--port", "8000"]
