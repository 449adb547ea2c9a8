FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY terrasift ./terrasift
RUN pip install --no-cache-dir .
ENV TERRASIFT_DATA_DIR=/data
VOLUME ["/data"]
EXPOSE 8000
CMD ["terrasift", "serve", "--host", "0.0.0.0", "--port", "8000"]
